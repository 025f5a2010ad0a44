"""The browser viewer (stage ``viewer``) of a finished run: data size, fidelity to the project's renders, frame time.

Its data's size and quantisation error, how close the page's frames are to the project's own renders, and its frame
time in headless Chromium (SwiftShader: a software renderer, so a floor, not a GPU's figure).

Reads ``methods/<method>/viewer/`` of an outputs folder (``make run``, or ``interactavatar quality=draft``). For the
training and held-out motions, at every capture camera and ``--frames`` frames spread over each motion, it draws the
frame in the page at the camera's size and renders it with the project's rasterizer: PSNR and SSIM (median, worst),
and whether the page's frame k is closer to the render of k than to those of k-2 and k+2. Then it plays each motion
for ``--play-s`` seconds at the page's default size and reports the page's median frame and posing times, with the
load average (the machine is shared). Tables are appended to ``benchmarks/results/bench_viewer.json``.

Usage: python benchmarks/bench_viewer.py --outputs outputs [--subject synth_a] [--method interactavatar]
       [--quality smoke] [--frames 3] [--play-s 4] [--results DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

from avatar.metrics import image_metrics  # noqa: E402
from benchmarks.provenance import ResultLog, add_results_argument  # noqa: E402
from benchmarks.viewer_browser import ProjectRender, chromium, manifest, open_viewer, psnr  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outputs", type=Path, required=True)
    parser.add_argument("--subject", default="synth_a")
    parser.add_argument("--method", default="interactavatar")
    parser.add_argument("--quality", default="smoke", help="the preset the outputs were made with")
    parser.add_argument("--frames", type=int, default=3, help="frames per motion and camera compared")
    parser.add_argument("--play-s", type=float, default=4.0, help="seconds each motion plays for the frame time")
    add_results_argument(parser)
    args = parser.parse_args()
    log = ResultLog("bench_viewer", preset=args.quality)
    subject = args.outputs / args.subject
    viewer_dir = subject / "methods" / args.method / "viewer"
    info = json.loads((viewer_dir / "viewer.json").read_text())
    page_manifest = manifest(viewer_dir)
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[f"quality={args.quality}", f"method={args.method}"])
    project = ProjectRender(subject, cfg, args.method, backend="auto")
    torch.set_num_threads(min(2, os.cpu_count() or 1))

    print(
        log.table(
            f"viewer data ({args.method}, {args.quality}): sizes on disk, error of the decoded Gaussians",
            ["motion", "frames", "kB/frame", "geometry overrides", "appearance overrides", "max mm", "max levels"],
            [
                (
                    m["name"],
                    m["frames"],
                    m["bytes_per_frame"] / 1e3,
                    m["geometry_overrides_per_frame"],
                    m["appearance_overrides_per_frame"],
                    m["errors"]["geometry_mm_max"],
                    max(m["errors"]["color_levels_max"], m["errors"]["opacity_levels_max"]),
                )
                for m in info["motions"]
            ]
            + [("all (avatar once + 100 frames)", "", f"{info['mb_per_100_frames']:.2f} MB", "", "", "", "")],
        )
    )
    rows, timing = [], []
    with chromium() as browser:
        with open_viewer(browser, f"{(viewer_dir / 'index.html').as_uri()}?scale=1") as page:
            for motion in page_manifest["motions"]:
                if motion["name"] not in ("train", "test"):
                    continue
                frames = sorted({int(f) for f in np.linspace(0, motion["frames"] - 1, args.frames).round()})
                for camera in motion["cameras"]:
                    scores, ordered = [], 0
                    for k in frames:
                        page.show(motion["name"], k, camera["id"])
                        shown = page.canvas()
                        ours = project.render(motion["name"], k, camera["id"])
                        m = image_metrics(
                            torch.from_numpy(shown).permute(2, 0, 1), torch.from_numpy(ours).permute(2, 0, 1), None
                        )
                        scores.append((m["psnr"], m["ssim"]))
                        neighbours = [j for j in (k - 2, k + 2) if 0 <= j < motion["frames"]]
                        ordered += all(
                            psnr(shown, ours) > psnr(shown, project.render(motion["name"], j, camera["id"]))
                            for j in neighbours
                        )
                    rows.append(
                        (
                            motion["name"],
                            camera["id"],
                            f"{camera['width']}x{camera['height']}",
                            statistics.median(s[0] for s in scores),
                            min(s[0] for s in scores),
                            statistics.median(s[1] for s in scores),
                            min(s[1] for s in scores),
                            f"{ordered}/{len(frames)}",
                        )
                    )
            assert page.errors == [], page.errors
        print(
            log.table(
                "the page's frame against the project's render at the capture camera (SwiftShader)",
                ["motion", "camera", "size", "PSNR median", "PSNR min", "SSIM median", "SSIM min", "frame k closest"],
                rows,
            )
        )
        with open_viewer(browser, (viewer_dir / "index.html").as_uri()) as page:
            size = page.page.evaluate(
                "[document.getElementById('render').width, document.getElementById('render').height]"
            )
            for motion in page_manifest["motions"]:
                page.page.select_option("#motion", motion["name"])
                page.page.wait_for_function(f"window.viewer.state.motion === {json.dumps(motion['name'])}")
                stats = page.frame_ms(args.play_s)
                timing.append((motion["name"], f"{size[0]}x{size[1]}", stats["frame_ms"], stats["pose_ms"]))
    print(
        log.table(
            f"frame time playing, headless Chromium in SwiftShader ({info['gaussians']} Gaussians; load "
            f"{os.getloadavg()[0]:.2f})",
            ["motion", "canvas", "frame ms (median)", "posing ms (median)"],
            timing,
        )
    )
    print(f"wrote {log.write(args.results)}")


if __name__ == "__main__":
    main()
