"""InteractAvatar against GaussianAvatars with seeds, on captures unlike the default (issue 40).

Settings (all at ``quality=draft``; every method trained once per seed, the shared stages once):

- ``a``: today's captures: ``full`` appearance, 24 training frames, ground-truth tracking; synth_a and synth_b;
- ``b``: ``plain`` appearance (no creases, no curl self-shadow, no contact darkening), otherwise as (a); synth_a;
- ``c``: ``full``, 8 training frames, fitted tracking on MediaPipe detections; synth_a (validation withholds 2 of 8 to
  choose on, then both stages train again on all 8: issue 53); ``c0``: the same without validation;
- ``e``: ``full``, 8 training frames, ground-truth tracking; synth_b (issue 53); ``e0``: the same without validation;
- ``a1``: (a) with ``validation.retrain=false`` (the validated runs written: the protocol before issue 53);
- ``ar``: (a) with ``stage.dynamic.restarts=2`` (issue 53: does the hand's seed spread shrink?);
- ``d``: the held-out third identity synth_c, ``full``, 24 frames, fitted tracking on MediaPipe detections;
- ``a2``: (a) with two threads per run instead of one (thread counts change the rounding of torch's reductions,
  which acts like another seed);
- ``h``: (a)'s captures and tracking, InteractAvatar with the paper's heads against ``stage.dynamic.heads=shared``
  (the method ``interactavatar_shared`` of benchmarks/conf/method/); ``hm``: the same on fitted MediaPipe tracking;
  ``table --settings h hm --name bench_heads_quality``;
- ``f``: (a)'s captures and tracking, InteractAvatar's networks in fp32 against ``run.precision=bf16`` (the method
  ``interactavatar_bf16`` of benchmarks/conf/method/; issue 58); ``fm``: the same on fitted MediaPipe tracking;
  ``table --settings f fm --name bench_precision``;
- ``p``: (a)'s captures and tracking, InteractAvatar against w/o PBD (issue 35: the methods table's "w/o PBD" rows
  against the contact ground truth of capture version 8); ``table --settings p --name bench_seeds_pbd``.

A setting compares InteractAvatar with GaussianAvatars unless it names another pair (``methods``).

``run`` trains and evaluates one setting's subject (``interactavatar -m method=... seed=...`` then the comparison
with ``stage.compare.seeds``) in ``<outputs>/<setting>/``, with the setting's thread count (``OMP_NUM_THREADS``:
1, or 2 for ``a2``); run two one-thread settings at once on a 2-core machine. ``table`` reads every comparison
under ``<outputs>`` and prints, per setting, subject, split and region, both methods' mean ± standard
deviation over the seeds, the difference of the means, the larger of the two spreads, Welch's p, and the
goal's verdict; and what the selection kept per seed (``kept_hand_mlp``, ``kept_interaction``,
``selected_step``). It writes ``benchmarks/results/bench_seeds.{json,md}`` with the commit,
machine, load and seeds.

Goal (issue 40): in no cell InteractAvatar worse than GaussianAvatars by more than the larger seed spread; in (a),
on the mean, at least +0.8 dB on the novel view's full image and +1.5 dB on its hand; in (b), the contact frames'
interaction region still gains.

Usage: python benchmarks/bench_seeds.py run --setting a --subject synth_a [--seeds 0 1 2] [--outputs DIR]
       python benchmarks/bench_seeds.py table [--outputs DIR] [--settings a b ...] [--name bench_seeds]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from avatar.metrics.stats import welch_p  # noqa: E402
from benchmarks.provenance import commit, cpu_name  # noqa: E402
from data_schemas.metrics import COMPARISON  # noqa: E402
from data_schemas.tables import read_table  # noqa: E402
from pipeline.summary import format_table  # noqa: E402
from pipeline.workspace import method_run  # noqa: E402

METHODS = ("interactavatar", "gaussian_avatars")
MEDIAPIPE = ["fit.source=fitted", "stage.keypoints.detector=mediapipe"]
# (m0) and (m1) predate refine_params and were measured without it (the code path without it is unchanged)
NO_TRAIN_REFINE = ["stage.warmup.refine_params=false", "stage.dynamic.refine_params=false"]
# issue 53's arm without validation: every frame trains, nothing is chosen
NO_VALIDATION = [
    "stage.warmup.validation.every=0",
    "stage.dynamic.validation.every=0",
    "stage.dynamic.select.enabled=false",
]
# the protocol before issue 53: the validated runs are written
NO_RETRAIN = ["stage.warmup.validation.retrain=false", "stage.dynamic.validation.retrain=false"]
#: the benchmarks' own methods (benchmarks/conf/method/: interactavatar_shared)
BENCH_METHODS = f"hydra.searchpath=[file://{REPO / 'benchmarks' / 'conf'}]"
SETTINGS: dict[str, dict] = {
    "a": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": ["fit.source=ground_truth"],
        "what": "full appearance, 24 frames, ground-truth tracking",
    },
    "b": {
        "subjects": ("synth_a",),
        "overrides": ["fit.source=ground_truth", "dataset.appearance=plain"],
        "what": "plain appearance, 24 frames, ground-truth tracking",
    },
    "c": {
        "subjects": ("synth_a",),
        "overrides": [*MEDIAPIPE, "quality.num_frames_train=8"],  # validation withholds 2 of 8 (fraction 0.15)
        "what": "full appearance, 8 frames, fitted tracking (MediaPipe)",
    },
    "c0": {
        "subjects": ("synth_a",),
        "overrides": [*MEDIAPIPE, "quality.num_frames_train=8", *NO_VALIDATION],
        "what": "as (c), no validation: nothing withheld, nothing chosen",
    },
    "a1": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": ["fit.source=ground_truth", *NO_RETRAIN],
        "what": "as (a), the validated runs written (withheld frames never trained on)",
    },
    "ar": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": ["fit.source=ground_truth", "stage.dynamic.restarts=2"],
        "what": "as (a), best of two initialisations of stage two (restarts)",
    },
    "e": {
        "subjects": ("synth_b",),
        "overrides": ["fit.source=ground_truth", "quality.num_frames_train=8"],
        "what": "full appearance, 8 frames, ground-truth tracking",
    },
    "e0": {
        "subjects": ("synth_b",),
        "overrides": ["fit.source=ground_truth", "quality.num_frames_train=8", *NO_VALIDATION],
        "what": "as (e), no validation: nothing withheld, nothing chosen",
    },
    "d": {
        "subjects": ("synth_c",),
        "overrides": [*MEDIAPIPE, "stage.capture.cross_reenactment=false"],
        "what": "held-out identity synth_c, 24 frames, fitted tracking (MediaPipe)",
    },
    "a2": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": ["fit.source=ground_truth"],
        "threads": 2,
        "what": "as (a), two threads per run",
    },
    "m0": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": [*MEDIAPIPE, "stage.fit.refine=none", *NO_TRAIN_REFINE],
        "what": "full appearance, 24 frames, fitted tracking (MediaPipe), keypoint fit only",
    },
    "m1": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": [*MEDIAPIPE, "stage.fit.refine=silhouette", *NO_TRAIN_REFINE],
        "what": "full appearance, 24 frames, fitted tracking (MediaPipe) refined by the train views' silhouettes",
    },
    "m2": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": [
            *MEDIAPIPE,
            "stage.fit.refine=silhouette",
            "stage.warmup.refine_params=true",
            "stage.dynamic.refine_params=true",
        ],
        "what": "as (m1), and the train motion refined with the avatar in training (refine_params)",
    },
    "h": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": ["fit.source=ground_truth", BENCH_METHODS],
        "methods": ("interactavatar", "interactavatar_shared"),
        "what": "full appearance, 24 frames, ground-truth tracking: the paper's heads against shared heads",
    },
    "hm": {
        "subjects": ("synth_a",),
        "overrides": [*MEDIAPIPE, BENCH_METHODS],
        "methods": ("interactavatar", "interactavatar_shared"),
        "what": "full appearance, 24 frames, fitted tracking (MediaPipe): the paper's heads against shared heads",
    },
    "f": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": ["fit.source=ground_truth", BENCH_METHODS],
        "methods": ("interactavatar", "interactavatar_bf16"),
        # run.* is the primary config's own (its _self_ comes last): a method's YAML cannot set it, the command can
        "method_overrides": {"interactavatar_bf16": ["run.precision=bf16"]},
        "what": "full appearance, 24 frames, ground-truth tracking: the networks in fp32 against run.precision=bf16",
    },
    "fm": {
        "subjects": ("synth_a",),
        "overrides": [*MEDIAPIPE, BENCH_METHODS],
        "methods": ("interactavatar", "interactavatar_bf16"),
        "method_overrides": {"interactavatar_bf16": ["run.precision=bf16"]},
        "what": "full appearance, 24 frames, fitted tracking (MediaPipe): the networks in fp32 against "
        "run.precision=bf16",
    },
    "p": {
        "subjects": ("synth_a", "synth_b"),
        "overrides": ["fit.source=ground_truth"],
        "methods": ("interactavatar", "no_pbd"),
        "what": "full appearance, 24 frames, ground-truth tracking, capture version 8: InteractAvatar against w/o PBD",
    },
}
REGIONS = (("full", "all"), ("hand", "all"), ("face", "all"), ("interaction", "all"), ("interaction", "contact"))
SPLITS = {"novel_view": "NV", "self_reenact": "SR"}


def _threads(spec: dict) -> int:
    return int(spec.get("threads", 1))


def _methods(spec: dict) -> tuple[str, str]:
    """The setting's (full model, baseline) pair."""
    return tuple(spec.get("methods", METHODS))


def _cli(threads: int, *args: str) -> None:
    """One run of the app with this checkout's code (the interpreter that runs this script), on ``threads``."""
    command = [sys.executable, "-m", "pipeline.cli", *args]
    print(f"$ OMP_NUM_THREADS={threads}", " ".join(command), flush=True)
    subprocess.run(command, cwd=REPO, check=True, env={**os.environ, "OMP_NUM_THREADS": str(threads)})


#: <outputs>/<setting>/quality.txt: the preset the setting's runs used (draft when absent: the committed figures)
QUALITY_FILE = "quality.txt"


def run(setting: str, subject: str, seeds: list[int], outputs: Path, extra: list[str], quality: str = "draft") -> None:
    """Train and evaluate both methods once per seed, then compare them (mean and spread over the seeds).
    ``quality`` is ``draft`` for every committed figure (``smoke`` only checks the path: ``make bench``)."""
    spec = SETTINGS[setting]
    (outputs / setting).mkdir(parents=True, exist_ok=True)
    (outputs / setting / QUALITY_FILE).write_text(quality)
    common = [
        f"paths.outputs={outputs / setting}",
        f"subject={subject}",
        f"quality={quality}",
        "run.progress=false",
        *spec["overrides"],
        *extra,
    ]
    seed_list, methods = ",".join(map(str, seeds)), ",".join(_methods(spec))
    own = spec.get("method_overrides", {})
    together = ",".join(m for m in _methods(spec) if m not in own)
    if together:
        _cli(_threads(spec), "-m", f"method={together}", f"seed={seed_list}", "run.until=evaluate", *common)
    for method, overrides in own.items():  # a method with overrides of its own: a multirun of its own
        _cli(_threads(spec), "-m", f"method={method}", f"seed={seed_list}", "run.until=evaluate", *common, *overrides)
    _cli(
        _threads(spec),
        "run.only=compare",
        f"stage.compare.methods=[{methods}]",
        f"stage.compare.seeds=[{seed_list}]",
        *common,
    )


def _manifest(path: Path) -> dict:
    return json.loads((path / "_manifest.json").read_text())


def _kept(subject_dir: Path, seeds: list[int], methods: tuple[str, str]) -> list[list[str]]:
    """What the selection kept, per method and seed."""
    rows = []
    for method in methods:
        for seed in seeds:
            folder = subject_dir / "methods" / method_run(method, seed) / "dynamic"
            if not (folder / "_manifest.json").is_file():
                continue
            m = _manifest(folder)["metrics"]
            rows.append(
                [
                    method,
                    str(seed),
                    str(m.get("selected_step", "-")),
                    str(m.get("selection_final_step", "-")),
                    str(m.get("kept_hand_mlp", "-")),
                    str(m.get("kept_interaction", "-")),
                    f"{m.get('selection_selected_psnr', float('nan')):.2f}",
                    f"{m.get('selection_final_psnr', float('nan')):.2f}",
                    f"{m.get('selection_psnr_without_hand_mlp', float('nan')):.2f}",
                    f"{m.get('selection_psnr_without_interaction', float('nan')):.2f}",
                ]
            )
    return rows


def _values(table: dict, method: str, split: str, region: str, group: str, metric: str) -> np.ndarray:
    sel = (
        (np.asarray(table["method"]) == method)
        & (np.asarray(table["split"]) == split)
        & (np.asarray(table["region"]) == region)
        & (np.asarray(table["contact"]) == group)
    )
    order = np.argsort(np.asarray(table["seed"])[sel])
    return np.asarray(table[metric], dtype=np.float64)[sel][order]


def _stat(v: np.ndarray, digits: int) -> str:
    if not v.size:
        return "-"
    return f"{v.mean():.{digits}f}" + (f" ± {v.std(ddof=1):.{digits}f}" if v.size > 1 else "")


def _setting_rows(setting: str, subject: str, table: dict, methods: tuple[str, str]) -> list[dict]:
    """Per split and region: both methods' PSNR and LPIPS over the seeds, the difference and the verdicts
    (``ia_*`` the full model's, ``ga_*`` the baseline's: ``methods``)."""
    out = []
    for split in SPLITS:
        for region, group in REGIONS:
            psnr = {m: _values(table, m, split, region, group, "psnr") for m in methods}
            lpips = {m: _values(table, m, split, region, group, "lpips") for m in methods}
            full, base = psnr[methods[0]], psnr[methods[1]]
            if not (full.size and base.size):
                continue
            diff = float(full.mean() - base.mean())
            spread = max(
                float(full.std(ddof=1)) if full.size > 1 else 0.0, float(base.std(ddof=1)) if base.size > 1 else 0.0
            )
            out.append(
                {
                    "setting": setting,
                    "subject": subject,
                    "split": split,
                    "region": region,
                    "group": group,
                    "seeds": int(min(full.size, base.size)),
                    "ia_psnr": full.tolist(),
                    "ga_psnr": base.tolist(),
                    "ia_lpips": lpips[methods[0]].tolist(),
                    "ga_lpips": lpips[methods[1]].tolist(),
                    "difference_db": diff,
                    "larger_sd_db": spread,
                    "welch_p": welch_p(full, base),
                    "worse_beyond_spread": bool(diff < -spread),
                }
            )
    return out


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


SUMMARY = (
    ("novel_view", "full", "all"),
    ("novel_view", "hand", "all"),
    ("novel_view", "interaction", "contact"),
    ("self_reenact", "full", "all"),
    ("self_reenact", "hand", "all"),
    ("self_reenact", "interaction", "contact"),
)


def summary(rows: list[dict], meta: dict) -> str:
    """One line per setting and subject: the differences of :data:`SUMMARY`'s cells and the cells that are worse
    beyond the spread (of every split and region)."""
    body = []
    for key, info in meta.items():
        setting, subject = key.split("/")
        mine = [r for r in rows if (r["setting"], r["subject"]) == (setting, subject)]
        cells = []
        for split, region, group in SUMMARY:
            r = next((r for r in mine if (r["split"], r["region"], r["group"]) == (split, region, group)), None)
            cells.append("-" if r is None else f"{r['difference_db']:+.2f} ({r['larger_sd_db']:.2f})")
        worse = [
            f"{SPLITS[r['split']]} {r['region']}{' (contact)' if r['group'] == 'contact' else ''}"
            for r in mine
            if r["worse_beyond_spread"]
        ]
        body.append([f"({setting})", subject, str(len(info["seeds"])), *cells, ", ".join(worse) or "none"])
    headers = (
        "setting",
        "subject",
        "seeds",
        *(f"{SPLITS[s]} {r}{' (contact)' if g == 'contact' else ''}" for s, r, g in SUMMARY),
        "worse beyond the spread",
    )
    return format_table(headers, body)


#: Labels of the methods a setting may compare.
LABELS = {"interactavatar": "InteractAvatar", "gaussian_avatars": "GaussianAvatars", "no_pbd": "w/o PBD"}


def table(outputs: Path, results: Path, settings: list[str], name: str) -> None:
    """Print the tables of ``settings`` (each compares one pair of methods; all of them the same pair) and write
    ``results/<name>.{md,json}``."""
    pairs = {_methods(SETTINGS[s]) for s in settings}
    if len(pairs) != 1:
        raise SystemExit(f"settings {settings} compare different method pairs {sorted(pairs)}: table them separately")
    methods = pairs.pop()
    full_label, base_label = (LABELS.get(m, m) for m in methods)
    rows, kept, meta = [], {}, {}
    for setting in settings:
        spec = SETTINGS[setting]
        for subject in spec["subjects"]:
            compare_dir = outputs / setting / subject / "compare"
            if not (compare_dir / "comparison.parquet").is_file():
                continue
            manifest = _manifest(compare_dir)
            seeds = [int(s) for s in manifest["config"]["stage.compare"]["seeds"]]
            t = read_table(compare_dir / "comparison.parquet", COMPARISON)
            rows += _setting_rows(setting, subject, t, methods)
            kept[f"{setting}/{subject}"] = _kept(outputs / setting / subject, seeds, methods)
            evaluate = _manifest(outputs / setting / subject / "methods" / methods[0] / "evaluate")
            quality_file = outputs / setting / QUALITY_FILE
            meta[f"{setting}/{subject}"] = {
                "quality": quality_file.read_text() if quality_file.is_file() else "draft",
                "seeds": seeds,
                "git": evaluate.get("git_sha", "?"),
                "what": spec["what"],
                "overrides": spec["overrides"],
                "threads": _threads(spec),
                "methods": list(methods),
            }
    if not meta:
        raise SystemExit(
            f"no comparison of settings {settings} under {outputs}: nothing written (run them first; "
            f"{results / name}.md keeps its earlier table)"
        )
    lines = [
        f"# {name}: {full_label} against {base_label} with seeds",
        "",
        f"Commit of this table: {commit()}; machine: {cpu_name()}, {os.cpu_count()} cores; load now: {_load()}; "
        f"made {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.",
        "",
        f"## Summary: {full_label}'s PSNR minus {base_label}'s (dB, difference of the seed means; in brackets "
        "the larger of the two seed standard deviations)",
        "",
        summary(rows, meta),
        "",
    ]
    for key, info in meta.items():
        setting, subject = key.split("/")
        lines += [
            f"## ({setting}) {subject}: {info['what']}",
            "",
            f"quality={info.get('quality', 'draft')} {' '.join(info['overrides'])}; seeds {info['seeds']}; "
            f"{info['threads']} thread(s) per run; trained at {info['git']}.",
            "",
        ]
        body = [
            [
                SPLITS[r["split"]],
                r["region"] + (" (contact)" if r["group"] == "contact" else ""),
                _stat(np.array(r["ia_psnr"]), 2),
                _stat(np.array(r["ga_psnr"]), 2),
                f"{r['difference_db']:+.2f}",
                f"{r['larger_sd_db']:.2f}",
                "-" if not np.isfinite(r["welch_p"]) else f"{r['welch_p']:.3f}",
                "WORSE"
                if r["worse_beyond_spread"]
                else ("gain" if r["welch_p"] < 0.05 and r["difference_db"] > 0 else "level"),
                _stat(np.array(r["ia_lpips"]), 4),
                _stat(np.array(r["ga_lpips"]), 4),
            ]
            for r in rows
            if (r["setting"], r["subject"]) == (setting, subject)
        ]
        lines += [
            format_table(
                (
                    "split",
                    "region",
                    f"{full_label} PSNR",
                    f"{base_label} PSNR",
                    "diff",
                    "larger sd",
                    "Welch p",
                    "verdict",
                    f"{full_label} LPIPS",
                    f"{base_label} LPIPS",
                ),
                body,
            ),
            "",
        ]
        lines += [
            "What stage two's selection kept:",
            "",
            format_table(
                (
                    "method",
                    "seed",
                    "kept step",
                    "of",
                    "H kept",
                    "I kept",
                    "val PSNR kept",
                    "val PSNR last",
                    "val w/o H",
                    "val w/o I",
                ),
                kept[key],
            ),
            "",
        ]
    lines += [
        f"verdict: WORSE where {full_label}'s mean is below {base_label}'s by more than the larger of the two "
        "seed standard deviations; gain where it is above with Welch's p < 0.05; level otherwise."
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    results.mkdir(parents=True, exist_ok=True)
    (results / f"{name}.md").write_text(text)
    (results / f"{name}.json").write_text(
        json.dumps(
            {
                "commit": commit(),
                "machine": cpu_name(),
                "cores": os.cpu_count(),
                "load": _load(),
                "settings": meta,
                "rows": rows,
                "kept": kept,
            },
            indent=1,
        )
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("--setting", choices=sorted(SETTINGS), required=True)
    r.add_argument("--subject", required=True)
    r.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    r.add_argument("--outputs", type=Path, default=REPO / "outputs" / "bench_seeds")
    r.add_argument("--quality", default="draft", help="draft for the figures; smoke checks the path")
    r.add_argument("extra", nargs="*", help="further overrides, e.g. run.lock_timeout_s=7200")
    t = sub.add_parser("table")
    t.add_argument("--outputs", type=Path, default=REPO / "outputs" / "bench_seeds")
    t.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    t.add_argument(
        "--settings",
        nargs="+",
        default=[k for k, v in SETTINGS.items() if "methods" not in v],
        choices=sorted(SETTINGS),
        help="settings to table (one method pair)",
    )
    t.add_argument("--name", default="bench_seeds", help="result file name under --results")
    args = parser.parse_args()
    if args.command == "run":
        if args.subject not in SETTINGS[args.setting]["subjects"]:
            parser.error(f"setting {args.setting} is measured on {SETTINGS[args.setting]['subjects']}")
        run(args.setting, args.subject, args.seeds, args.outputs.resolve(), args.extra, args.quality)
    else:
        table(args.outputs.resolve(), args.results, args.settings, args.name)


if __name__ == "__main__":
    main()
