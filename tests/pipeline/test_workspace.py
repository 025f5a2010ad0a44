"""The workspace's leftovers clean-up touches only the artifact it is asked about.

Regression: with seeds, method ``interactavatar`` and run ``interactavatar-seed2`` train side by side; the
clean-up of ``evaluate@interactavatar`` globbed ``evaluate@interactavatar-*`` and deleted the temporary dir
that the concurrent seed-2 run was writing (``stage did not write its declared output(s) ['splits.json']``),
and the seed-2 stage two's checkpoints with it.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.workspace import Artifact, Workspace, method_run


def test_a_seed_runs_temporary_and_scratch_dirs_survive_the_clean_up_of_seed_zero(tmp_path: Path):
    ws = Workspace(tmp_path, "synth_a")
    seed0 = Artifact("evaluate", method_run("interactavatar", 0))
    seed2 = Artifact("evaluate", method_run("interactavatar", 2))
    busy_tmp = ws.new_tmp_dir(seed2)
    (busy_tmp / "splits.json").write_text("{}")
    busy_scratch = ws.scratch_dir(seed2, "ab" * 32)
    (busy_scratch / "dynamic.pt").write_bytes(b"checkpoint")
    stale_tmp, stale_scratch = ws.new_tmp_dir(seed0), ws.scratch_dir(seed0, "cd" * 32)

    fresh = ws.new_tmp_dir(seed0)  # what the runner calls before writing seed 0's artifact
    ws.discard_leftovers(seed0)  # and after publishing it

    assert (busy_tmp / "splits.json").is_file(), "seed 2's artifact being written was deleted"
    assert (busy_scratch / "dynamic.pt").is_file(), "seed 2's checkpoint was deleted"
    assert not stale_tmp.exists() and not stale_scratch.exists() and not fresh.exists()


def test_a_published_artifacts_old_version_is_set_aside_and_removed(tmp_path: Path):
    ws = Workspace(tmp_path, "s")
    art = Artifact("warmup", "m")
    for text in ("old", "new"):
        tmp = ws.new_tmp_dir(art)
        (tmp / "v.txt").write_text(text)
        final = ws.publish(art, tmp)
    assert (final / "v.txt").read_text() == "new"
    assert not list((tmp_path / "s" / ".tmp").iterdir())


def test_publishing_over_a_linked_stage_folder_replaces_the_link_and_leaves_its_target(tmp_path: Path):
    """A stage folder the user linked elsewhere: a forced rerun used to leave the link in .tmp for good
    (``shutil.rmtree`` refuses links); now the link goes, a real folder takes its place, the target stays."""
    ws = Workspace(tmp_path / "out", "s")
    art = Artifact("fit")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "v.txt").write_text("old")
    final = ws.artifact_dir(art)
    final.parent.mkdir(parents=True)
    for target in (elsewhere, tmp_path / "gone"):  # a link, then a dangling link
        final.symlink_to(target, target_is_directory=True)
        tmp = ws.new_tmp_dir(art)
        (tmp / "v.txt").write_text("new")
        assert ws.publish(art, tmp) == final
        assert not final.is_symlink() and (final / "v.txt").read_text() == "new"
        assert not list((tmp_path / "out" / "s" / ".tmp").iterdir()), "the link stayed in .tmp"
        shutil.rmtree(final)
    assert (elsewhere / "v.txt").read_text() == "old"


def test_a_linked_leftover_in_tmp_is_removed_without_touching_its_target(tmp_path: Path):
    ws = Workspace(tmp_path / "out", "s")
    art = Artifact("fit")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.txt").write_text("keep")
    ws.new_tmp_dir(art).rmdir()  # creates .tmp
    (tmp_path / "out" / "s" / ".tmp" / f"fit-old-{'a' * 12}").symlink_to(elsewhere, target_is_directory=True)
    ws.discard_leftovers(art)
    assert not list((tmp_path / "out" / "s" / ".tmp").iterdir())
    assert (elsewhere / "keep.txt").read_text() == "keep"


def test_a_full_disk_is_no_outputs_problem(tmp_path: Path, monkeypatch) -> None:
    """Where no folder can be made because the disk is full (ext4 needs a block for one; tmpfs does not), the
    outputs are still usable for a run that finds every stage cached: the stage that must write says so."""
    import errno

    from pipeline.workspace import outputs_problem

    def full(self: Path, *args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "mkdir", full)
    assert outputs_problem(tmp_path / "out") is None
