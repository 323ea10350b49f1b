"""A scene's pages for the Snakemake report: its forecast videos on one HTML
page (the report shows HTML inline; an mp4 result is only a download there),
in a folder beside the videos it plays, and one figure of the quality of the
model the forecasts start from (grouping against the ground-truth instance
masks, reconstruction at held-out views of observed times).

The folder goes into the report as an HTML index with its files, which only a
zipped report (`--report results/report.zip`) can hold: an embedded HTML
report would carry the page as a data: URL, and browsers refuse to load one
of more than 2 MB into a frame."""

from __future__ import annotations

import html
import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import atomic_folder, atomic_path
from ..errors import input_error
from .table_format import HTML_PAGE
from .tables import METHOD_ORDER, method_label

VIDEO_SUFFIXES = (".mp4", ".gif")


def _read_metrics(path: str | os.PathLike) -> dict[str, Any]:
    from .metrics_files import load_metrics

    return load_metrics([path])[0]


def _video_files(renders: Path) -> list[Path]:
    """all_methods first, then one per method in the tables' order (mp4, or gif where ffmpeg was missing)."""
    files = {p.stem: p for p in sorted(renders.iterdir()) if p.suffix in VIDEO_SUFFIXES and p.is_file()}
    order = ["all_methods"] + [m for m in METHOD_ORDER if m in files] + sorted(set(files) - set(METHOD_ORDER))
    return [files[name] for name in dict.fromkeys(order) if name in files]


def videos_page(renders: str | os.PathLike, metrics: str | os.PathLike, out_dir: str | os.PathLike) -> Path:
    """`out_dir`/index.html: every video of `renders` (copied beside it), each
    under its method's label, playable in the page."""
    renders = Path(renders)
    if not renders.is_dir():
        raise input_error(renders, "missing (the evaluate stage writes the videos here)")
    result = _read_metrics(metrics)
    files = _video_files(renders)
    if not files:
        raise input_error(renders, "holds no video (evaluate.video is off?); nothing to put on the page")
    title = f"{result['dataset']}/{result['scene']}, ratio {result['ratio']:g}"
    if result.get("variant") not in (None, "default"):
        title += f", variant {result['variant']}"
    parts = [
        f"<h3>Forecasts: {html.escape(title)}</h3>",
        "<p>Ground truth, forecast and error at the held-out views of the forecast time steps; "
        "every panel is labelled, the caption gives the time step and the view.</p>",
    ]
    for path in files:
        name = path.stem
        label = "All methods beside the ground truth" if name == "all_methods" else method_label(result, name)
        src = html.escape(path.name)
        if path.suffix == ".gif":
            media = f'<img src="{src}" alt="{html.escape(label)}">'
        else:
            media = f'<video controls loop muted autoplay playsinline preload="auto" src="{src}"></video>'
        parts.append(f"<figure><figcaption>{html.escape(label)}</figcaption>{media}</figure>")
    page = HTML_PAGE.format(title=html.escape(title), body="\n".join(parts))
    with atomic_folder(out_dir) as tmp:
        for path in files:
            shutil.copyfile(path, tmp / path.name)
        (tmp / "index.html").write_text(page, encoding="utf-8")
    return Path(out_dir)


def quality_figure(
    grouping_quality: str | os.PathLike, reconstruction_quality: str | os.PathLike, out_png: str | os.PathLike
) -> Path:
    """Two panels: IoU of each ground-truth object with its best group (and
    the ARI), and the reconstruction's PSNR / SSIM per held-out view at
    observed times."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..grouping.quality import read_grouping_quality
    from ..reconstruction_quality.stage import read_per_frame

    grouping = read_grouping_quality(grouping_quality)
    recon = read_per_frame(reconstruction_quality)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6))
    names = list(grouping.get("object_names", []))
    if names:
        names += list(grouping.get("part_names", []))
        ious = list(grouping["per_object_iou"]) + list(grouping.get("per_part_iou", []))
        left.bar(range(len(names)), ious, color="#4c72b0")
        left.set_xticks(range(len(names)), [str(n) for n in names], rotation=30, ha="right", fontsize=8)
        left.set_ylim(0, 1)
        left.set_ylabel("IoU with its best group")
        ari = grouping.get("ari")
        extra = f", ARI {ari:.2f}" if isinstance(ari, (int, float)) else ""
        left.set_title(f"Grouping ({grouping.get('method')}): {grouping.get('num_groups')} groups{extra}", fontsize=9)
    else:
        left.text(0.5, 0.5, "no ground-truth instance masks:\ngrouping not measured", ha="center", va="center")
        left.set_axis_off()
    if "psnr" in recon["per_frame"] and recon["timesteps"].size:
        reconstruction_panel(right, recon)
    else:
        right.text(0.5, 0.5, "no held-out view at an observed time:\nreconstruction not measured", ha="center")
        right.set_axis_off()
    fig.tight_layout()
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return Path(out_png)


# Most held-out cameras the reconstruction panel draws a line each for (matplotlib's colour cycle).
PANEL_CAMERAS = 10


def reconstruction_panel(ax: Any, recon: Mapping[str, Any]) -> list[Any]:
    """PSNR (and SSIM on a second axis) over the observed time steps, one
    line per held-out camera: a scene's held-out views differ in how well
    the training views cover them, so one line through frames of alternating
    cameras would zigzag between their levels. One line through every frame
    where there are no camera ids, where a camera has a single frame (a
    camera per frame, as D-NeRF's test views) or more than PANEL_CAMERAS
    cameras. `recon`: read_per_frame's. Returns the PSNR lines."""
    per_frame, steps = recon["per_frame"], recon["timesteps"]
    cameras = recon.get("camera_ids")
    # (label, rows) of each line
    series = [("PSNR", np.arange(steps.size))]
    if cameras is not None:
        ids, counts = np.unique(cameras, return_counts=True)
        # a camera per frame (D-NeRF's test views) or more than the colours: one line over time
        if counts.min() >= 2 and ids.size <= PANEL_CAMERAS:
            series = [(f"camera {int(c)}", np.flatnonzero(cameras == c)) for c in ids]
    twin = None
    if "ssim" in per_frame:
        twin = ax.twinx()
        twin.set_ylabel("SSIM (dashed)")
        twin.set_ylim(0, 1)
    lines = []
    for k, (label, rows) in enumerate(series):  # (at most PANEL_CAMERAS)
        rows = rows[np.argsort(steps[rows], kind="stable")]
        colour = f"C{k}"
        lines += ax.plot(steps[rows], per_frame["psnr"][rows], "o-", color=colour, label=label, markersize=4)
        if twin is not None:
            twin.plot(steps[rows], per_frame["ssim"][rows], "s--", color=colour, markersize=3, alpha=0.6)
    ax.set_xlabel("observed time step")
    ax.set_ylabel("PSNR [dB] (solid)")
    ax.set_title(f"Reconstruction at held-out views: mean PSNR {float(np.mean(per_frame['psnr'])):.2f} dB", fontsize=9)
    ax.grid(alpha=0.3)
    if len(lines) > 1:
        ax.legend(fontsize=7, loc="best")
    return lines


def scene_report(
    renders: str | os.PathLike,
    metrics: str | os.PathLike,
    grouping_quality: str | os.PathLike,
    reconstruction_quality: str | os.PathLike,
    out_videos: str | os.PathLike,
    out_quality: str | os.PathLike,
) -> list[Path]:
    """The scene's videos page and quality figure."""
    return [
        videos_page(renders, metrics, out_videos),
        quality_figure(grouping_quality, reconstruction_quality, out_quality),
    ]
