"""The report's sections on training: the contact frames' draws, the frames withheld for validation, what the
selection kept, the loss and validation curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from data_schemas import web_escape as esc
from data_schemas.curve import CURVE
from data_schemas.tables import TableSchema, read_table
from reporting.html import figure_png, png_image, pyplot


def contact_draws_paragraph(dynamic: dict) -> str:
    """How often stage two drew the contact frames (stage.dynamic.contact_fraction, capped by
    max_contact_emphasis); nothing for a manifest from before the cap or without contact frames."""
    p = dynamic["metrics"].get("contact_draw_probability")
    conf = dynamic["config"].get("stage.dynamic", {})
    if p is None or not dynamic["metrics"].get("contact_frames") or "contact_fraction" not in conf:
        return ""
    fraction = float(conf["contact_fraction"])
    text = f"Stage two drew a contact frame first with probability {p:.2f}, else any training frame"
    if p < fraction and "max_contact_emphasis" in conf:
        text += (
            f" (contact_fraction {fraction:g}, lowered so that no contact frame is drawn more than "
            f"{float(conf['max_contact_emphasis']):g} times as often as a frame without contact: with few contact "
            "frames the Gaussians would fit their tracking error)"
        )
    return f"<p>{esc.text(text)}.</p>"


def withheld_paragraph(dynamic: dict) -> str:
    """What validation withheld and what the written model trained on (``validation_frames_withheld``,
    ``final_training_frames``); nothing for a manifest from before they were recorded."""
    metrics, conf = dynamic["metrics"], dynamic["config"].get("stage.dynamic", {})
    withheld, final = metrics.get("validation_frames_withheld"), metrics.get("final_training_frames")
    validation = conf.get("validation", {})
    if withheld is None or final is None or not int(validation.get("every", 0)):
        return ""
    if not withheld:
        text = (
            f"Nothing could be withheld for validation: with {final} training frames, at least "
            f"{validation.get('min_train_frames')} must stay to train on (stage.dynamic.validation.min_train_frames), "
            "so stage two trained on all of them and chose nothing"
        )
    elif metrics.get("retrained_on_all_frames"):
        text = (
            f"Validation withheld {withheld} of {final} training frames (fraction {validation.get('fraction')}) to "
            f"choose on; the model shown was then trained again on all {final} frames with what was chosen"
        )
    else:
        text = (
            f"Validation withheld {withheld} training frames (fraction {validation.get('fraction')}); the model shown "
            f"trained on the other {final} (stage.dynamic.validation.retrain=false)"
        )
    return f"<p>{esc.text(text)}.</p>"


def selection_paragraph(dynamic: dict) -> str:
    """What stage two's selection kept (stage.dynamic.select), on the validation figures it rests on; nothing
    when it did not run."""
    if "selected_step" not in dynamic:
        return "<p>Stage two kept its last step and every module it built (stage.dynamic.select.enabled=false).</p>"
    step, final = int(dynamic["selected_step"]), int(dynamic["selection_final_step"])
    text = (
        f"Stage two kept step {step} of {final}"
        + (" (the warm-up's model: H and I at zero)" if step == 0 else "")
        + f": validation PSNR {dynamic['selection_selected_psnr']:.2f} dB against "
        f"{dynamic['selection_final_psnr']:.2f} dB at the last step, on training frames that neither stage "
        "trained on."
    )
    for module, name in (("hand_mlp", "the hand MLPs H"), ("interaction", "the interaction MLPs I")):
        without = dynamic.get(f"selection_psnr_without_{module}")
        if without is None:
            text += f" {name[0].upper()}{name[1:]}: not built."
            continue
        kept = bool(dynamic[f"kept_{module}"])
        if dynamic.get(f"selection_judged_{module}") is False:
            text += (
                f" {name[0].upper()}{name[1:]}: kept without being judged (none of the withheld frames has "
                "contact, which they model)."
            )
            continue
        text += (
            f" {name[0].upper()}{name[1:]}: {'kept' if kept else 'switched off'} (validation PSNR without them "
            f"{without:.2f} dB)."
        )
    if "restarts" in dynamic:
        text += (
            f" Best of {dynamic['restarts']} initialisations of stage two on validation (kept: number "
            f"{int(dynamic['selected_restart']) + 1}, seed {dynamic['selected_seed']})."
        )
    return f"<p>{esc.text(text)} Rule: docs/explanation/selection.md.</p>"


def dynamic_summary(manifest: dict) -> str:
    """One sentence on the dynamic stage's cost: steps, ms per step, interaction-MLP evaluations."""
    m = manifest["metrics"]
    if "interaction_steps" not in m:  # SplattingAvatar: no MLPs
        return esc.text(
            f"{m['steps']} steps at {m['ms_per_step']:.0f} ms each, {m.get('walked', 0)} triangle changes by walking"
        )
    return esc.text(
        f"{m['steps']} steps at {m['ms_per_step']:.0f} ms each; the interaction MLPs ran in "
        f"{m['interaction_steps']} steps on {m['interaction_mlp_evaluations']} Gaussians in all"
    )


def loss_curve(train_dir: Path, schema: TableSchema, terms: tuple[str, ...]) -> str:
    """Base64 PNG of the loss ``terms`` of a stage's ``train_log.parquet`` against steps."""
    plt = pyplot()
    log = read_table(train_dir / "train_log.parquet", schema)
    fig, ax = plt.subplots(figsize=(6, 3), dpi=100)
    for name in terms:
        ax.plot(log["step"], log[name], label=name)
    ax.set_xlabel("step")
    ax.set_yscale("log")
    ax.legend()
    return figure_png(fig)


def validation_section(warmup_dir: Path, dynamic_dir: Path) -> str:
    """The validation curves of the two training stages (stage.*.validation), one time axis: nothing when
    neither validated."""
    curves = {
        name: read_table(d / "curve.parquet", CURVE)
        for name, d in (("warm-up", warmup_dir), ("stage two", dynamic_dir))
        if (d / "curve.parquet").is_file()
    }
    curves = {name: c for name, c in curves.items() if len(c["step"])}
    if not curves:
        return (
            "<p>No validation curve: stage.warmup.validation.every and stage.dynamic.validation.every "
            "are 0 (docs/how-to/quality-during-training.md).</p>"
        )
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3), dpi=100)
    with_lpips = any(np.isfinite(np.asarray(c["lpips"], float)).any() for c in curves.values())
    ax_lpips = ax.twinx() if with_lpips else None
    offset = 0.0
    for name, curve in curves.items():
        wall = np.asarray(curve["wall_s"], float) + offset
        (line,) = ax.plot(wall, curve["psnr"], marker=".", label=name)
        if ax_lpips is not None:  # validation.lpips: dashed, same colour, right axis
            ax_lpips.plot(wall, curve["lpips"], linestyle="--", marker=".", color=line.get_color())
        offset = float(wall[-1])
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel("validation PSNR (dB)")
    if ax_lpips is not None:
        ax_lpips.set_ylabel("validation LPIPS (dashed)")
    ax.legend()
    title = "Validation PSNR" + (" and LPIPS" if with_lpips else "")
    return f"<h3>{title} during training (withheld training frames, training cameras)</h3>" + png_image(
        "validation curve", figure_png(fig)
    )
