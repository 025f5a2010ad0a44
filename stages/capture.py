"""Stage ``capture``: generate the synthetic capture, or validate and import one on disk (a folder in the
capture layout, or the DECAF release: ``importers.decaf_capture``)."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from omegaconf import DictConfig

from avatar.artifacts.dependencies import model_files
from data_schemas.cameras import Camera, read_cameras, write_cameras
from data_schemas.capture import (
    CaptureIndex,
    SequenceInfo,
    cross_sequence,
    gt_path,
    mask_path,
    video_path,
)
from data_schemas.deform import DEFORM
from data_schemas.images import write_png
from data_schemas.keypoints import write_keypoints
from data_schemas.params import PARAM_COLUMNS, PARAMS
from data_schemas.sources import SourceFiles
from data_schemas.tables import SchemaError, write_table
from data_schemas.video import write_video
from pipeline.stage import StageContext, stage

if TYPE_CHECKING:
    from avatar.synthetic import SyntheticCapture, SyntheticConfig

SEQUENCES = ("train", "test")
#: prctl option: the signal a process receives when its parent dies (linux/prctl.h).
_PR_SET_PDEATHSIG = 1
#: Rendered (supersampled) pixels of a whole capture below which its sequences render in this process: each
#: worker first imports torch and the generator (seconds), which costs more than a small capture saves.
#: Measured on 2 cores at load ~5: smoke (4 M pixels) 13-14 s serial against 21 s in 2 workers; draft
#: (100 M) 130 s against 101 s.
PARALLEL_MIN_PIXELS = 20_000_000


@dataclass
class CaptureConfig:
    """Types of ``stage.capture`` (values in conf/stage/capture.yaml)."""

    num_cameras: int
    default_frame_rate: float
    cross_reenactment: bool


def capture_sources(cfg: DictConfig, subject: str) -> SourceFiles:
    """The user files a capture imports, whose content enters its cache key: every file of the subject's
    folder (dataset=folder), or the subject's part of the DECAF release and the official model files
    (dataset=decaf); none for the synthetic generator."""
    dataset = cfg.dataset
    if dataset.name == "folder":
        root = Path(dataset.root) / subject
        return SourceFiles(root, _files_below(root))
    if dataset.name == "decaf":
        root = Path(dataset.root)
        files = [f for folder in sorted(root.glob(f"*/*/{subject}")) for f in _files_below(folder)]
        neck = root / "assets" / "FLAME_neck_idx.npy"
        return SourceFiles(root, (*files, *([neck] if neck.is_file() else []), *model_files(cfg)))
    return SourceFiles(Path("."), ())


def capture_checks(cfg: DictConfig) -> list[str]:
    """What the capture cannot be made or imported with, found before any stage runs: for the synthetic generator
    a subject, scene or appearance it does not know; for a capture on disk, a subject folder that is not there and,
    for a folder capture, sequence folders and camera names that cannot name artifact paths
    (``importers.folder.name_problems``)."""
    dataset = cfg.dataset
    if dataset.get("name") == "synthetic":
        return _synthetic_problems(cfg)
    if not dataset.get("root"):  # unset: the config check says so
        return []
    if dataset.get("name") == "decaf":
        from importers.decaf_capture import decaf_subject_problem  # FLAME, torch: DECAF captures only

        problem = decaf_subject_problem(Path(str(dataset.root)), str(cfg.subject))
        return [] if problem is None else [problem]
    if dataset.get("name") != "folder":
        return []
    from importers.folder import name_problems, subject_folder_problem  # COLMAP, nerfstudio: folder only

    src = Path(str(dataset.root)) / str(cfg.subject)
    problem = subject_folder_problem(src, str(cfg.subject))
    return name_problems(src) if problem is None else [problem]


def _synthetic_problems(cfg: DictConfig) -> list[str]:
    """``subject``, ``dataset.scene`` and ``dataset.appearance`` values the generator does not know, one line each."""
    from avatar.synthetic.capture import APPEARANCES, SCENES, SUBJECTS

    subjects = tuple(dict.fromkeys((*cfg.dataset.get("subjects", ()), *SUBJECTS)))
    problems = [] if cfg.subject in subjects else [_choice_problem("subject", cfg.subject, subjects)]
    for key, known in (("scene", SCENES), ("appearance", APPEARANCES)):
        value = cfg.dataset.get(key)
        if value is not None and value not in known:
            problems.append(_choice_problem(f"dataset.{key}", value, known))
    return problems


def _choice_problem(key: str, value: object, known: tuple[str, ...]) -> str:
    return f"{key}={value}: not in the synthetic dataset; choose one of {', '.join(known)}"


def _files_below(folder: Path) -> tuple[Path, ...]:
    return tuple(sorted(p.resolve() for p in folder.rglob("*") if p.is_file())) if folder.is_dir() else ()


@stage(
    "capture",
    config_keys=(
        "dataset",
        "quality.capture_size",
        "quality.num_frames_train",
        "quality.num_frames_test",
        "quality.supersample",
        "stage.capture",
    ),
    outputs=("cameras.parquet", "capture.json"),
    version="8",
    config_schema=CaptureConfig,
    sources=capture_sources,
    checks=capture_checks,
)
def capture(ctx: StageContext) -> None:
    """Generate (synthetic) or validate and import (folder, decaf) a multi-view capture."""
    dataset = ctx.cfg.dataset
    if dataset.name == "synthetic":
        index = _generate_synthetic(ctx)
    elif dataset.name == "folder":
        from importers.folder import import_folder  # COLMAP, nerfstudio, undistortion: folder captures only

        index = import_folder(dataset, ctx.subject, ctx.out_dir, float(ctx.cfg.stage.capture.default_frame_rate))
    elif dataset.name == "decaf":
        from importers.decaf_capture import import_decaf  # pulls in torch (FLAME), which folder captures never need

        index = import_decaf(dataset, ctx.subject, ctx.out_dir, float(ctx.cfg.stage.capture.default_frame_rate))
    else:
        raise SchemaError(
            f"dataset.name={dataset.name!r}: unknown dataset; use dataset=synthetic, dataset=folder or dataset=decaf"
        )
    if dataset.get("train_cameras") is not None:
        _train_only(ctx.out_dir / "cameras.parquet", [str(c) for c in dataset.train_cameras])
    index.write(ctx.out_dir)
    cameras = read_cameras(ctx.out_dir / "cameras.parquet")
    ctx.metrics["cameras"] = len(cameras)
    ctx.metrics["train_cameras"] = sum(c.split == "train" for c in cameras)
    for name, seq in index.sequences.items():
        ctx.metrics[f"{name}_frames"] = seq.num_frames
        if seq.provided:
            ctx.metrics[f"{name}_provided"] = "+".join(seq.provided)


# ---------------------------------------------------------------------------- synthetic
def _generate_synthetic(ctx: StageContext) -> CaptureIndex:
    # Imported here: the generator pulls in torch, which folder captures and cached runs never need.
    from avatar.synthetic import SyntheticConfig

    q, conf = ctx.cfg.quality, ctx.cfg.stage.capture
    problems = _synthetic_problems(ctx.cfg)  # checked before any stage ran; again for a caller of the stage alone
    if problems:
        raise SchemaError("; ".join(problems))
    frames_per_sequence = {"train": q.num_frames_train, "test": q.num_frames_test}
    # name -> (script, performer): the two sequences, and with stage.capture.cross_reenactment this identity
    # performing every other subject's held-out motion (the ground truth of cross-actor reenactment); every
    # sequence stages dataset.scene
    plan = {seq: (seq, None) for seq in SEQUENCES}
    if conf.cross_reenactment:
        plan |= {cross_sequence(other): ("test", other) for other in ctx.cfg.dataset.subjects if other != ctx.subject}
    configs = {
        seq: SyntheticConfig(
            subject=ctx.subject,
            sequence=script,
            image_size=int(q.capture_size),
            num_frames=int(frames_per_sequence[script]),
            supersample=int(q.supersample),
            seed=int(ctx.cfg.dataset.seed),
            num_cameras=int(conf.num_cameras),
            performer=performer,
            scene=str(ctx.cfg.dataset.scene),
            appearance=str(ctx.cfg.dataset.get("appearance", "full")),
        )
        for seq, (script, performer) in plan.items()
    }
    rendered = _render_sequences(ctx, configs)
    sequences: dict[str, SequenceInfo] = {}
    for seq in configs:  # plan order, whatever order the workers finished in
        info = rendered[seq]
        sequences[seq] = SequenceInfo(
            num_frames=info.num_frames,
            frame_rate=info.frame_rate,
            width=info.cameras[0].width,
            height=info.cameras[0].height,
            has_masks=True,
            has_ground_truth=True,
        )
        ctx.metrics[f"{seq}_contact_frames"] = info.contact_frames
    write_cameras(ctx.out_dir / "cameras.parquet", rendered[next(iter(configs))].cameras)
    return CaptureIndex(subject=ctx.subject, dataset="synthetic", sequences=sequences)


@dataclass(frozen=True)
class _Rendered:
    """What the stage keeps of a sequence once its files are written (small: it crosses process borders)."""

    cameras: list[Camera]
    num_frames: int
    frame_rate: float
    contact_frames: int


def _render_sequences(ctx: StageContext, configs: dict[str, SyntheticConfig]) -> dict[str, _Rendered]:
    """Generate and write every sequence of ``configs`` (name -> generator config) into the stage's folder.

    The sequences are independent (each is seeded by seed, subject and script), so they render in parallel
    worker processes, as many as torch's thread budget allows (each generator runs on one thread): the files
    are byte-identical to a serial run. One thread, one sequence, or a capture under
    :data:`PARALLEL_MIN_PIXELS` renders in this process.
    """
    import torch  # the generator's dependency, like avatar.synthetic

    pixels = sum(c.num_frames * c.num_cameras * (c.image_size * c.supersample) ** 2 for c in configs.values())
    workers = min(len(configs), torch.get_num_threads()) if pixels >= PARALLEL_MIN_PIXELS else 1
    jobs = [(ctx.out_dir, seq, cfg) for seq, cfg in configs.items()]
    desc = "capture: generating sequences"
    if workers <= 1:
        return dict(_render_sequence(*job) for job in ctx.progress(jobs, desc=desc))
    # spawn, not fork: a forked child of a process whose OpenMP pool has started can hang in it
    pool = ProcessPoolExecutor(
        workers, mp_context=multiprocessing.get_context("spawn"), initializer=_die_with_parent, initargs=(os.getpid(),)
    )
    started: list[multiprocessing.process.BaseProcess] = []
    try:
        with _spawning_workers(started):  # submit starts the workers
            futures = [pool.submit(_render_sequence, *job) for job in jobs]
        rendered = dict(future.result() for future in ctx.progress(as_completed(futures), desc=desc, total=len(jobs)))
    except BaseException:  # Ctrl-C, a worker's error: the workers stop now, mid-sequence (their files are discarded)
        _stop_workers(pool, started)
        raise
    pool.shutdown()
    return rendered


@contextmanager
def _spawning_workers(started: list[multiprocessing.process.BaseProcess]) -> Iterator[None]:
    """While the block starts worker processes (appended to ``started``): SIGINT is blocked in this thread, so each
    worker starts with it blocked and a Ctrl-C during its start-up (seconds of imports) stays pending until its
    initializer ignores it (:func:`_die_with_parent`); a Ctrl-C meant for this process is held until the workers
    have started, none half, and raised here then as KeyboardInterrupt (in the main thread, where Python handles
    signals)."""
    before = set(multiprocessing.active_children())
    held: list[int] = []
    main = threading.current_thread() is threading.main_thread()
    handler = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum)) if main else None
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        started.extend(set(multiprocessing.active_children()) - before)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a Ctrl-C that came meanwhile is delivered now: held
        if main:  # a handler Python did not set (None) is put back as the default action
            signal.signal(signal.SIGINT, signal.SIG_DFL if handler is None else handler)
    if held:
        raise KeyboardInterrupt


def _stop_workers(pool: ProcessPoolExecutor, workers: list[multiprocessing.process.BaseProcess]) -> None:
    """End ``pool`` without waiting for its work: its queued jobs cancelled, its ``workers`` terminated (SIGTERM, at
    any point of their start-up or work) and reaped."""
    pool.shutdown(wait=False, cancel_futures=True)
    for worker in workers:
        worker.terminate()
    for worker in workers:
        worker.join()


def _die_with_parent(parent_pid: int) -> None:
    """Worker initializer: a killed run leaves no worker writing into its scratch folder. On Linux the kernel
    sends SIGKILL to the worker when the stage's process dies (``PR_SET_PDEATHSIG``); a worker whose parent
    is already gone exits at once. Elsewhere the pool's own shutdown is all there is. A worker ignores Ctrl-C
    (SIGINT to the terminal's process group), also one that came while it started (:func:`_spawning_workers`):
    the stage's process stops the workers (:func:`_stop_workers`) and says in one line what was kept, and no worker
    prints a traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # a pending Ctrl-C is dropped: it is ignored now
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent_pid:
        os._exit(1)


def _render_sequence(root: Path, seq: str, cfg: SyntheticConfig) -> tuple[str, _Rendered]:
    """Generate one sequence and write its files under ``root`` (runs in a worker process)."""
    from avatar.synthetic import generate

    cap = generate(cfg)
    _write_synthetic_sequence(root, seq, cap)
    return seq, _Rendered(
        cameras=cap.cameras,
        num_frames=len(cap.contact),
        frame_rate=cap.frame_rate,
        contact_frames=int(cap.contact.sum()),
    )


def _write_synthetic_sequence(root: Path, seq: str, cap: SyntheticCapture) -> None:
    num_frames = len(cap.contact)
    for cam in cap.cameras:
        write_video(video_path(root, seq, cam.camera_id), cap.frames[cam.camera_id], cap.frame_rate)
        for t in range(num_frames):
            write_png(mask_path(root, seq, cam.camera_id, t), cap.masks[cam.camera_id][t])
    frames = np.arange(num_frames)
    write_table(gt_path(root, seq, "params"), PARAMS, {"frame": frames, **{k: cap.params[k] for k in PARAM_COLUMNS}})
    write_keypoints(gt_path(root, seq, "keypoints"), cap.keypoints, num_frames)
    write_table(
        gt_path(root, seq, "deform"),
        DEFORM,
        {"frame": frames, "contact": cap.contact, "offsets": cap.face_offsets.reshape(num_frames, -1)},
    )


def _train_only(path: Path, train: list[str]) -> None:
    """``dataset.train_cameras``: train on these cameras only (one makes a monocular capture); every other
    camera is held out for novel views."""
    cameras = read_cameras(path)
    ids = [c.camera_id for c in cameras]
    unknown = sorted(set(train) - set(ids))
    if unknown or not train or set(train) >= set(ids):
        raise SchemaError(f"dataset.train_cameras={train}: choose some but not all of the cameras {ids}")
    write_cameras(path, [replace(c, split="train" if c.camera_id in train else "test") for c in cameras])
