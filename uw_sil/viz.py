"""Figures a person looks at: contact sheets of frames, renders, depth and masks (matplotlib, Agg)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ._shared.fileio import atomic_path

__all__ = ["contact_sheet", "depth_image", "display_gain", "gain_words", "pyplot", "save_figure"]


def pyplot():
    """matplotlib.pyplot on the Agg backend (headless; imported on first use)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 110) -> Path:
    """Save atomically (temp file + rename) and close the figure."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    finally:
        pyplot().close(fig)
    return Path(path)


#: Largest brightening of a figure's images (deep-sea frames lit by the vehicle's lamps sit at a few grey levels).
MAX_DISPLAY_GAIN = 16


def display_gain(image01, target: float = 0.7) -> int:
    """Brightening for showing a dark frame (values 0-1): the power of two, 1 to :data:`MAX_DISPLAY_GAIN`, that
    lifts the frame's 99.5th percentile closest to ``target`` without passing it. A deep-sea frame whose panel
    sits at 5-20 grey levels is black on a screen; the same gain on the recording and on its simulations keeps
    them comparable, and the figure says it (:func:`gain_words`). Never a darkening, so frames that are bright
    already are shown as they are."""
    a = np.asarray(image01, np.float32)
    a = a[np.isfinite(a)]
    p = float(np.percentile(a, 99.5)) if a.size else 0.0
    if p <= 0.0:
        return MAX_DISPLAY_GAIN
    k = int(np.floor(np.log2(target / p))) if target > p else 0
    return int(2 ** min(max(k, 0), int(np.log2(MAX_DISPLAY_GAIN))))


def gain_words(gain: int) -> str:
    """A figure title's note of :func:`display_gain` ("" at 1)."""
    return f", shown ×{gain}" if gain > 1 else ""


def depth_image(depth: np.ndarray) -> np.ma.MaskedArray:
    """Depth with no-hit pixels masked, for ``imshow`` with a colour bar."""
    d = np.asarray(depth, dtype=float)
    return np.ma.masked_invalid(np.where(np.isfinite(d), d, np.nan))


def contact_sheet(rows, title: str = ""):
    """A grid: one row per frame with the recorded (real-like) image (brightened when dark, :func:`display_gain`),
    clean render, depth and label mask.

    Parameters
    ----------
    rows : iterable of (label, image_uint8, render)
        ``render`` has ``rgb``, ``depth`` and ``labels`` (a :class:`uw_sil.sim.render.RenderResult`).
    """
    plt = pyplot()
    rows = list(rows)
    if not rows:
        raise ValueError("contact sheet needs at least one frame")
    fig, axes = plt.subplots(len(rows), 4, figsize=(13, 2.6 * len(rows)), squeeze=False)
    for ax_row, (label, img, rr) in zip(axes, rows):
        g = display_gain(np.asarray(img, np.float32) / 255.0)
        ax_row[0].imshow(np.clip(g * (np.asarray(img, np.float32) / 255.0), 0, 1))
        ax_row[0].set_title(f"recorded {label}{gain_words(g)}", fontsize=9)
        ax_row[1].imshow(np.clip(rr.rgb, 0, 1))
        ax_row[1].set_title("clean render", fontsize=9)
        im = ax_row[2].imshow(depth_image(rr.depth), cmap="viridis")
        ax_row[2].set_title("depth z [m]", fontsize=9)
        fig.colorbar(im, ax=ax_row[2], fraction=0.035, pad=0.02)
        ax_row[3].imshow(rr.labels, cmap="tab10", vmin=0, vmax=9, interpolation="nearest")
        ax_row[3].set_title("labels (0 water, 1 panel, 2 seafloor)", fontsize=9)
        for ax in ax_row:
            ax.set_xticks([])
            ax.set_yticks([])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
