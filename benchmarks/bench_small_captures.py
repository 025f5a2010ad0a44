"""Small captures: choosing on withheld frames, then training on every frame, against no validation (issue 53).

Reads what ``benchmarks/bench_seeds.py run`` trained for the paired settings of :data:`PAIRS` (each a setting with
today's protocol and the same capture without validation: ``c``/``c0``, synth_a with 8 frames and MediaPipe tracking;
``e``/``e0``, synth_b with 8 frames and ground-truth tracking), every method once per seed, and prints:

1. per setting, method, split and region: the protocol's PSNR and LPIPS against the arm without validation (mean ±
   standard deviation over the seeds), the difference and the larger spread; goal (issue 53): never below beyond the
   spread;
2. InteractAvatar's gain over GaussianAvatars in the contact frames' interaction region per arm, against its gain on
   setting (a) (``benchmarks/results/bench_seeds.json``); goal: at least 70 % of it;
3. per run: what the selection kept, the contact draw probability, the frames withheld and trained on, and the two
   training stages' wall time (the protocol's cost: the median ratio of the protocol's to the arm without validation).

It writes ``benchmarks/results/bench_small_captures.{md,json}`` with the commit, machine, load and seeds.

Usage (``run`` trains both settings of a pair with ``bench_seeds.py``; run the two pairs side by side, one thread each,
on a 2-core machine):
    python benchmarks/bench_small_captures.py run --pair e [--seeds 0 1 2] [--outputs DIR]
    python benchmarks/bench_small_captures.py table [--outputs DIR] [--results DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from benchmarks.bench_seeds import LABELS, METHODS, REGIONS, SETTINGS, SPLITS, _stat, _values, run  # noqa: E402
from benchmarks.provenance import commit, cpu_name  # noqa: E402
from data_schemas.metrics import COMPARISON  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.summary import format_table  # noqa: E402
from pipeline.workspace import method_run  # noqa: E402

#: (setting with validation, the same without): bench_seeds.py's settings
PAIRS = (("e", "e0"), ("c", "c0"))
#: settings with the protocol on the 24-frame captures, shown beside setting (a) of bench_seeds.json (measured before
#: the protocol): (a) itself retrained with it, and (ar) with two restarts
LARGE = ("a", "a1", "ar")
#: the cell whose gain issue 53 compares with setting (a)'s
CONTACT_CELL = ("novel_view", "interaction", "contact")


def _comparison(outputs: Path, setting: str) -> tuple[str, dict, list[int]] | None:
    """(subject, comparison table, seeds) of a setting's run, or None when it has none."""
    for subject in SETTINGS[setting]["subjects"]:
        folder = outputs / setting / subject / "compare"
        if (folder / "comparison.parquet").is_file():
            seeds = json.loads((folder / "_manifest.json").read_text())["config"]["stage.compare"]["seeds"]
            return subject, read_table(folder / "comparison.parquet", COMPARISON), [int(s) for s in seeds]
    return None


def _protocol_rows(pair: tuple[str, str], subject: str, with_val: dict, without: dict) -> list[dict]:
    """Per method, split and region: the protocol's PSNR/LPIPS against the arm without validation."""
    rows = []
    for method in METHODS:
        for split in SPLITS:
            for region, group in REGIONS:
                a, b = (_values(t, method, split, region, group, "psnr") for t in (with_val, without))
                la, lb = (_values(t, method, split, region, group, "lpips") for t in (with_val, without))
                if not (a.size and b.size):
                    continue
                spread = max(float(a.std(ddof=1)) if a.size > 1 else 0.0, float(b.std(ddof=1)) if b.size > 1 else 0.0)
                diff = float(a.mean() - b.mean())
                rows.append(
                    {
                        "setting": pair[0],
                        "baseline_setting": pair[1],
                        "subject": subject,
                        "method": method,
                        "split": split,
                        "region": region,
                        "group": group,
                        "protocol_psnr": a.tolist(),
                        "no_validation_psnr": b.tolist(),
                        "protocol_lpips": la.tolist(),
                        "no_validation_lpips": lb.tolist(),
                        "difference_db": diff,
                        "larger_sd_db": spread,
                        "below_beyond_spread": bool(diff < -spread),
                    }
                )
    return rows


#: the cells of the methods' comparison per arm: (split, region, group)
GAIN_CELLS = (
    ("novel_view", "full", "all"),
    ("novel_view", "face", "all"),
    ("self_reenact", "full", "all"),
    ("self_reenact", "face", "all"),
    ("self_reenact", "hand", "all"),
    CONTACT_CELL,
)


def _gain(table: dict, cell: tuple[str, str, str]) -> tuple[float, float]:
    """InteractAvatar's mean PSNR minus GaussianAvatars' in ``cell`` (split, region, group), and the larger of the two
    seed standard deviations."""
    full, base = (_values(table, m, *cell, "psnr") for m in METHODS)
    if not (full.size and base.size):
        return float("nan"), float("nan")
    spread = max(float(v.std(ddof=1)) if v.size > 1 else 0.0 for v in (full, base))
    return float(full.mean() - base.mean()), spread


def _reference_gains(results: Path) -> dict[str, float]:
    """Setting (a)'s contact interaction gain per subject, from bench_seeds.json."""
    path = results / "bench_seeds.json"
    if not path.is_file():
        return {}
    rows = json.loads(path.read_text())["rows"]
    return {
        r["subject"]: r["difference_db"]
        for r in rows
        if r["setting"] == "a" and (r["split"], r["region"], r["group"]) == CONTACT_CELL
    }


def _large_rows(outputs: Path, results: Path) -> list[list[str]]:
    """InteractAvatar minus GaussianAvatars on the 24-frame settings of :data:`LARGE` trained with the protocol, beside
    bench_seeds.json's (a) (the protocol before issue 53), and InteractAvatar's hand spread."""
    path = results / "bench_seeds.json"
    before = json.loads(path.read_text())["rows"] if path.is_file() else []
    out = []
    for setting in LARGE:
        for subject in SETTINGS[setting]["subjects"]:
            folder = outputs / setting / subject / "compare"
            if not (folder / "comparison.parquet").is_file():
                continue
            table = read_table(folder / "comparison.parquet", COMPARISON)
            for cell in (*GAIN_CELLS, ("novel_view", "hand", "all")):
                diff, spread = _gain(table, cell)
                hand = _values(table, METHODS[0], *cell, "psnr")
                old = next(
                    (
                        r
                        for r in before
                        if (r["setting"], r["subject"], r["split"], r["region"], r["group"]) == ("a", subject, *cell)
                    ),
                    None,
                )
                out.append(
                    [
                        f"({setting})",
                        subject,
                        f"{SPLITS[cell[0]]} {cell[1]}{' contact' if cell[2] == 'contact' else ''}",
                        f"{diff:+.2f} ({spread:.2f})",
                        "-" if old is None else f"{old['difference_db']:+.2f} ({old['larger_sd_db']:.2f})",
                        f"{hand.std(ddof=1):.2f}" if hand.size > 1 else "-",
                        "-" if old is None else f"{np.std(old['ia_psnr'], ddof=1):.2f}",
                    ]
                )
    return out


def _run_rows(outputs: Path, setting: str, subject: str, seeds: list[int]) -> list[list[str]]:
    """Per method and seed: what stage two kept and drew, the frames withheld and trained on, the stages' wall time."""
    rows = []
    for method in METHODS:
        for seed in seeds:
            stages = outputs / setting / subject / "methods" / method_run(method, seed)
            manifests = {}
            for stage in ("warmup", "dynamic"):
                path = stages / stage / "_manifest.json"
                if path.is_file():
                    manifests[stage] = json.loads(path.read_text())
            if len(manifests) < 2:
                continue
            m = manifests["dynamic"]["metrics"]
            rows.append(
                [
                    setting,
                    method,
                    str(seed),
                    str(m.get("selected_step", "-")),
                    str(m.get("kept_hand_mlp", "-")),
                    str(m.get("kept_interaction", "-")),
                    f"{m.get('contact_draw_probability', float('nan')):.2f}",
                    str(m.get("validation_frames_withheld", "-")),
                    str(m.get("final_training_frames", "-")),
                    f"{manifests['warmup']['timings'].get('wall_s', float('nan')):.0f}",
                    f"{manifests['dynamic']['timings'].get('wall_s', float('nan')):.0f}",
                ]
            )
    return rows


def _cost(runs: list[list[str]], pair: tuple[str, str]) -> str:
    """The median wall time of warm-up plus stage two with the protocol over that without validation."""
    totals = {s: [float(r[9]) + float(r[10]) for r in runs if r[0] == s] for s in pair}
    if not all(totals.values()):
        return "-"
    return f"{np.median(totals[pair[0]]) / np.median(totals[pair[1]]):.2f}"


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def report(outputs: Path, results: Path) -> None:
    """Print the tables of :data:`PAIRS` found under ``outputs`` and write ``results/bench_small_captures.*``."""
    reference = _reference_gains(results)
    rows, gains, runs, meta = [], [], [], {}
    for pair in PAIRS:
        found = [_comparison(outputs, s) for s in pair]
        if not all(found):
            continue
        (subject, with_val, seeds), (_, without, seeds0) = found  # type: ignore[misc]
        rows += _protocol_rows(pair, subject, with_val, without)
        for setting, table, arm_seeds in ((pair[0], with_val, seeds), (pair[1], without, seeds0)):
            cells = [_gain(table, cell) for cell in GAIN_CELLS]
            ref = reference.get(subject, float("nan"))
            gains.append(
                [
                    f"({setting})",
                    subject,
                    *(f"{d:+.2f} ({s:.2f})" for d, s in cells),
                    f"{ref:+.2f}",
                    f"{cells[-1][0] / ref:.0%}",
                ]
            )
            runs += _run_rows(outputs, setting, subject, arm_seeds)
        meta[f"{pair[0]}/{subject}"] = {
            "seeds": seeds,
            "what": SETTINGS[pair[0]]["what"],
            "overrides": SETTINGS[pair[0]]["overrides"],
            "without": SETTINGS[pair[1]]["overrides"],
        }
    for setting in LARGE:
        found = _comparison(outputs, setting)
        if found is not None:
            runs += _run_rows(outputs, setting, found[0], found[2])
    if not meta:
        raise SystemExit(f"no paired comparison of {PAIRS} under {outputs}: run bench_seeds.py's settings first")
    lines = [
        "# bench_small_captures: choosing on withheld frames, then training on every frame, against no validation",
        "",
        f"Commit of this table: {commit()}; machine: {cpu_name()}, {os.cpu_count()} cores; load now: {_load()}; "
        f"made {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. quality=draft, one thread per run.",
        "",
    ]
    for key, info in meta.items():
        setting, subject = key.split("/")
        lines += [
            f"## ({setting}) {subject}: {info['what']}; seeds {info['seeds']}",
            "",
            f"Protocol: `{' '.join(info['overrides'])}` (today's defaults); without validation: "
            f"`{' '.join(info['without'])}`.",
            "",
        ]
        body = [
            [
                LABELS.get(r["method"], r["method"]),
                SPLITS[r["split"]],
                r["region"] + (" (contact)" if r["group"] == "contact" else ""),
                _stat(np.array(r["protocol_psnr"]), 2),
                _stat(np.array(r["no_validation_psnr"]), 2),
                f"{r['difference_db']:+.2f}",
                f"{r['larger_sd_db']:.2f}",
                "BELOW" if r["below_beyond_spread"] else "ok",
                _stat(np.array(r["protocol_lpips"]), 4),
                _stat(np.array(r["no_validation_lpips"]), 4),
            ]
            for r in rows
            if (r["setting"], r["subject"]) == (setting, subject)
        ]
        headers = (
            "method",
            "split",
            "region",
            "protocol PSNR",
            "no validation PSNR",
            "diff",
            "larger sd",
            "verdict",
            "protocol LPIPS",
            "no validation LPIPS",
        )
        lines += [format_table(headers, body), ""]
    lines += [
        "## InteractAvatar's PSNR minus GaussianAvatars' per arm (dB; in brackets the larger seed sd)",
        "",
        "NV contact: the novel view's interaction region in contact frames, against the same gain on setting (a) "
        "(24 frames, ground-truth tracking; benchmarks/results/bench_seeds.json); goal: at least 70 % of it.",
        "",
        format_table(
            (
                "setting",
                "subject",
                *(f"{SPLITS[s]} {r}{' contact' if g == 'contact' else ''}" for s, r, g in GAIN_CELLS),
                "NV contact on (a)",
                "share",
            ),
            gains,
        ),
        "",
        "## The 24-frame captures with the protocol",
        "",
        "InteractAvatar's PSNR minus GaussianAvatars' (dB; larger seed sd in brackets): (a) with the protocol, (a1) "
        "the same capture with the validated runs written (validation.retrain=false: the withheld frames never "
        "trained on), (ar) the protocol with the best of two initialisations; beside bench_seeds.json's (a) "
        "(validated runs written, an older commit); and InteractAvatar's seed sd in the same cell.",
        "",
        format_table(
            ("setting", "subject", "cell", "IA - GA", "IA - GA before", "IA sd", "IA sd before"),
            _large_rows(outputs, results),
        ),
        "",
        "## Per run: what stage two kept and drew, what was withheld, and the cost",
        "",
        format_table(
            (
                "setting",
                "method",
                "seed",
                "kept step",
                "H kept",
                "I kept",
                "contact draw p",
                "withheld",
                "trained on",
                "warmup s",
                "dynamic s",
            ),
            runs,
        ),
        "",
        "Warm-up plus stage two, median wall time with the protocol over without validation: "
        + ", ".join(f"({p[0]}) {_cost(runs, p)}" for p in PAIRS)
        + ".",
        "",
        "verdict: BELOW where the protocol's mean is below the arm without validation by more than the larger of "
        "the two seed standard deviations; ok otherwise.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    results.mkdir(parents=True, exist_ok=True)
    (results / "bench_small_captures.md").write_text(text)
    payload = {
        "commit": commit(),
        "machine": cpu_name(),
        "cores": os.cpu_count(),
        "load": _load(),
        "settings": meta,
        "rows": rows,
        "gains": gains,
        "runs": runs,
    }
    (results / "bench_small_captures.json").write_text(json.dumps(payload, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("--pair", choices=[p[0] for p in PAIRS], required=True)
    r.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    r.add_argument("--outputs", type=Path, default=REPO / "outputs" / "bench_seeds")
    r.add_argument("--quality", default="draft", help="draft for the figures; smoke checks the path")
    r.add_argument("extra", nargs="*", help="further overrides, e.g. run.lock_timeout_s=7200")
    t = sub.add_parser("table")
    t.add_argument("--outputs", type=Path, default=REPO / "outputs" / "bench_seeds")
    t.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    if args.command == "run":
        for setting in next(p for p in PAIRS if p[0] == args.pair):
            run(setting, SETTINGS[setting]["subjects"][0], args.seeds, args.outputs.resolve(), args.extra, args.quality)
    else:
        report(args.outputs.resolve(), args.results)


if __name__ == "__main__":
    main()
