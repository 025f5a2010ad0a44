"""A run on a full disk: one that finds every stage cached writes nothing and succeeds; one that must compute
stops with one line naming the disk and the fix, leaves nothing half written and keeps the last artifact."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import TOY_OVERRIDES, fill_disk, run_cli, small_disk

TOY = [*TOY_OVERRIDES, "run.progress=false"]


def test_a_cached_run_on_a_full_disk_succeeds_and_a_computing_one_is_one_line(tmp_path: Path) -> None:
    with small_disk(tmp_path / "disk", 2048) as disk:
        out = disk / "out"
        first = run_cli(*TOY, f"paths.outputs={out}")
        assert first.returncode == 0, first.stderr
        before = (out / "synth_a" / "b" / "b.txt").read_text()
        fill_disk(disk)

        cached = run_cli(*TOY, f"paths.outputs={out}")
        assert cached.returncode == 0, cached.stderr
        assert all(f"{s}          cached" in cached.stdout for s in "abcd"), cached.stdout

        forced = run_cli(*TOY, f"paths.outputs={out}", "run.only=b", "run.force=true")
        assert forced.returncode == 1
        assert "Traceback" not in forced.stderr
        lines = [line for line in forced.stderr.splitlines() if line.strip()]
        assert len(lines) == 1, forced.stderr
        assert "No space left on device" in lines[0]
        assert f"the disk of {out / 'synth_a'} is full: free some space, then run the same command again" in lines[0]
        assert (out / "synth_a" / "b" / "b.txt").read_text() == before
        assert not list((out / "synth_a" / ".tmp").iterdir())
        assert not list((out / "synth_a" / ".scratch").iterdir())
