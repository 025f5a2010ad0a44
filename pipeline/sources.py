"""Content digests of a stage's source files outside the artifact tree (a capture folder on disk).

A stage that imports user files (``capture`` with ``dataset=folder`` or ``decaf``)
declares them; their sha256 enters its cache key, so a replaced or edited video
reruns the import and everything below it. Hashing a large capture on every run
would be slow, so a digest is reused while the file's size, modification time
and inode are unchanged (the check ``make`` and ``rsync`` rely on); a file edited
in place while keeping all three is not noticed.
"""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

from data_schemas.sources import SourceFiles
from pipeline.manifest import sha256_file


def _stamp(st: os.stat_result) -> list[int]:
    return [st.st_size, st.st_mtime_ns, st.st_ino]


def hash_sources(sources: SourceFiles, cache_path: Path) -> dict[str, str]:
    """relative posix path -> sha256 of every source file, reusing ``cache_path``'s digests of unchanged files.

    The cache (absolute path -> size, mtime, inode, digest) is rewritten atomically; a
    concurrent run writing it too only loses the other's additions.
    """
    try:
        cache: dict[str, list] = json.loads(cache_path.read_text())
    except (OSError, ValueError):
        cache = {}
    digests: dict[str, str] = {}
    changed = False
    for path in sorted(sources.files):
        stamp = _stamp(path.stat())
        hit = cache.get(str(path))
        if hit is not None and hit[:3] == stamp:
            digest = hit[3]
        else:
            digest = sha256_file(path)
            if _stamp(path.stat()) != stamp:
                raise OSError(
                    f"{path}: the file changed while it was being hashed; wait until it is "
                    f"written completely, then rerun"
                )
            cache[str(path)] = [*stamp, digest]
            changed = True
        digests[path.relative_to(sources.root).as_posix() if path.is_relative_to(sources.root) else str(path)] = digest
    if changed:
        cache_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache_path.with_name(f"{cache_path.name}.{uuid.uuid4().hex[:8]}.tmp")
        tmp.write_text(json.dumps(cache, sort_keys=True))
        os.replace(tmp, cache_path)
    return digests


def changed_sources(old: dict[str, str], new: dict[str, str], limit: int = 3) -> list[str]:
    """Relative paths added, removed or edited between two source digests (at most ``limit``, then '...')."""
    names = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    return names[:limit] + (["..."] if len(names) > limit else [])
