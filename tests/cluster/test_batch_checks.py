"""The cluster tests' own checks, on job output written here (runs in ``make test``; no cluster needed)."""

from __future__ import annotations

from tests.cluster.batch import Submission, computed_once, every_stage

JOB_A = """\
(_run_job pid=101) [synth_a] capture    run       outputs missing: never run
(_run_job pid=101) [synth_a] frames     cached    key matches
(_run_job pid=101) [synth_a/interactavatar] warmup     run       outputs missing: never run
"""
JOB_B = """\
[synth_a] capture    cached    key matches
[synth_a] frames     run       outputs missing: never run
[synth_a/no_patch] warmup     shared    same key as method interactavatar: its artifact is shared
stage      action    wall_s  peak MB  reason
capture    cached    -       -        cached
"""


def _submission(output: str) -> Submission:
    return Submission(returncode=0, driver_output="", job_output=output, wall_s=1.0)


def test_decisions_are_read_from_ray_prefixed_and_plain_job_output():
    decisions = _submission(JOB_A + JOB_B).decisions()
    assert decisions[("synth_a", None, "capture", "run")] == 1
    assert decisions[("synth_a", None, "capture", "cached")] == 1
    assert decisions[("synth_a", "interactavatar", "warmup", "run")] == 1
    assert decisions[("synth_a", "no_patch", "warmup", "shared")] == 1
    assert sum(decisions.values()) == 6  # the summary table's rows are not decisions


def test_computed_once_flags_a_stage_computed_twice_or_never():
    sub = _submission(JOB_A + JOB_B)
    assert computed_once(sub, "synth_a", ["capture", "frames", "warmup"]) == {}
    twice = _submission(JOB_A + JOB_A)
    assert set(computed_once(twice, "synth_a", ["capture", "frames"])) == {"capture", "frames"}


def test_every_stage_lists_what_was_not_cached():
    sub = _submission(JOB_B)
    missing = every_stage("cached", sub, ["synth_a"])
    assert "synth_a/capture" not in missing and "synth_a/frames" in missing and "synth_a/report" in missing
