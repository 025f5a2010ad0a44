"""``interactavatar --help`` is the app's own page; Hydra's stays one flag away (issue 36, item 8)."""

from __future__ import annotations

from tests.conftest import run_cli


def test_help_is_the_apps_own_page_and_hydras_is_one_flag_away() -> None:
    own = run_cli("--help", timeout=120)
    assert own.returncode == 0, own.stderr
    for expected in (
        "hand-face interaction avatars",
        "run.only=STAGE",
        "run.dry=true",
        "quality=smoke|draft",
        "method: gaussian_avatars, interactavatar",
        "--hydra-help",
        "README.md",
    ):
        assert expected in own.stdout, expected
    assert len(own.stdout.splitlines()) < 80  # no config dump (Hydra's page printed ~400 lines)
    hydra = run_cli("--hydra-help", timeout=120)
    assert hydra.returncode == 0 and "Hydra" in hydra.stdout
