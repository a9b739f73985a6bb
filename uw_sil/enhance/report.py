"""The forward half's figures and report section: the paper's Fig. 4 (recorded | DCP | UDCP | SIL, and the
clean render when the truth is known), Fig. 5 (feature matches between two frames, per method) and
Table 2 (matches per descriptor and method), plus the quality table of synthetic trials.

:func:`write_forward_report` writes ``fig4_enhancement.png``, ``fig5_matches.png``, ``features.csv``,
``quality.csv`` and ``forward.html`` into a report directory, and links the section from the directory's
``index.html`` (the backward fit's report) when there is one.
"""
from __future__ import annotations

import csv
import html
import re
from pathlib import Path
from typing import Optional

import numpy as np

from .._shared.fileio import atomic_path, write_text_atomic
from ..viz import pyplot, save_figure

__all__ = ["enhancement_figure", "matches_figure", "write_forward_report", "write_rows_csv"]

_ORDER = ("raw", "dcp", "udcp", "sil")
_TITLES = {"raw": "recorded", "dcp": "DCP (He et al.)", "udcp": "UDCP (Drews et al.)", "sil": "SIL (this model)"}


def enhancement_figure(frames, images, show_truth: bool = True, quality: Optional[list] = None):
    """Fig. 4 analogue: one row per frame, columns recorded | DCP | UDCP | SIL (| clean render).

    ``frames``: ``[(index, sample, render)]``; ``images``: ``[{method: uint8 image}]``; ``quality`` rows of
    :func:`uw_sil.enhance.bagtool.quality_rows` add PSNR/SSIM to the titles.
    """
    plt = pyplot()
    cols = [m for m in _ORDER if m in images[0]] + (["truth"] if show_truth else [])
    q = {(r["frame"], r["method"]): r for r in (quality or [])}
    from .bagtool import LABELS

    fig, axes = plt.subplots(len(frames), len(cols), figsize=(3.3 * len(cols), 3.1 * len(frames)), squeeze=False)
    for row, ((i, s, geo), d) in zip(axes, zip(frames, images)):
        crop = _panel_crop(geo.labels > 0)
        for ax, m in zip(row, cols):
            if m == "truth":
                ax.imshow(np.clip(geo.rgb, 0, 1)[crop])
                ax.set_title(f"clean render (truth), #{i}", fontsize=9)
            else:
                ax.imshow(d[m][crop])
                title = f"{_TITLES[m]}, #{i}"
                r = q.get((i, LABELS[m]))
                if r is not None and np.isfinite(r["psnr_db"]):
                    title += f"\nPSNR {r['psnr_db']:.1f} dB, SSIM {r['ssim']:.3f} (panel)"
                ax.set_title(title, fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("Fig. 4 analogue: recorded frames and their enhancements (cropped around the panel)", fontsize=10)
    fig.tight_layout()
    return fig


def _panel_crop(obj: np.ndarray, margin: float = 0.35) -> tuple:
    """Slices of the object's bounding box grown by ``margin`` of its size on each side (whole frame if none)."""
    ys, xs = np.nonzero(obj)
    if ys.size == 0:
        return (slice(None), slice(None))
    h, w = obj.shape
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    dy, dx = int(margin * (y1 - y0)) + 8, int(margin * (x1 - x0)) + 8
    return (slice(max(0, y0 - dy), min(h, y1 + dy)), slice(max(0, x0 - dx), min(w, x1 + dx)))


def matches_figure(frames, images, descriptor: str = "SIFT", max_lines: int = 60):
    """Fig. 5 analogue: the two frames side by side with their verified matches (green), per method."""
    from .bagtool import LABELS
    from .features import draw_matches, match_features

    plt = pyplot()
    methods = [m for m in _ORDER if m in images[0]]
    fig, axes = plt.subplots(len(methods), 1, figsize=(9, 3.6 * len(methods)), squeeze=False)
    for ax, m in zip(axes[:, 0], methods):
        a, b = images[0][m], images[1][m]
        r = match_features(a, b, descriptor)
        ax.imshow(draw_matches(a, b, r, max_lines=max_lines))
        ax.set_title(f"{LABELS[m]}: {descriptor}, {r.n_verified} verified of {r.n_raw} raw matches "
                     f"(frames #{frames[0][0]} and #{frames[1][0]}; the {max_lines} closest drawn)", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    return fig


def write_rows_csv(rows, path) -> Path:
    """Dict rows as CSV (columns of the first row), atomically."""
    if not rows:
        raise ValueError("no rows to write")
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return Path(path)


def _md_to_html_table(md: str) -> str:
    lines = [ln for ln in md.strip().splitlines() if ln.startswith("|")]
    if len(lines) < 2:
        return f"<pre>{html.escape(md)}</pre>"
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cells[0])
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in cells[2:])
    note = "".join(f"<p><small>{html.escape(ln)}</small></p>" for ln in md.strip().splitlines()
                   if ln.strip() and not ln.startswith("|"))
    return f"<table border=1 cellpadding=3><tr>{head}</tr>{body}</table>{note}"


def write_forward_report(out_dir, frames, images, feature_rows: list, feature_markdown: str,
                         quality: Optional[list] = None, quality_markdown: str = "", descriptor: str = "SIFT",
                         title: str = "uw_sil forward half", notes: str = "") -> Path:
    """Write the forward half's figures, CSVs and ``forward.html`` into ``out_dir`` (see module docstring).

    ``frames``/``images``: the frames shown in Fig. 4 (the first two are the matched pair of Fig. 5)."""
    from .features import table_csv

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_figure(enhancement_figure(frames, images, show_truth=quality is not None, quality=quality),
                out / "fig4_enhancement.png")
    save_figure(matches_figure(frames[:2], images[:2], descriptor), out / "fig5_matches.png")
    table_csv(feature_rows, out / "features.csv")
    if quality:
        write_rows_csv(quality, out / "quality.csv")
    qsec = ""
    if quality:
        qsec = (f"<h2>Against the truth (synthetic trial)</h2><p>PSNR and SSIM against the clean render on the "
                f"panel's pixels; UIQM and UCIQE (no reference) of the whole frame.</p>"
                f"{_md_to_html_table(quality_markdown)}<p><a href='quality.csv'>quality.csv</a></p>")
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title></head>
<body style="font-family: sans-serif; max-width: 1400px">
<h1>{html.escape(title)}</h1>
<p>{html.escape(notes)}</p>
<h2>Fig. 4 analogue: recorded, DCP, UDCP and SIL</h2><img src="fig4_enhancement.png" style="max-width:100%">
{qsec}
<h2>Table 2 analogue: feature matches between frames #{frames[0][0]} and #{frames[1][0]}</h2>
{_md_to_html_table(feature_markdown)}<p><a href="features.csv">features.csv</a></p>
<h2>Fig. 5 analogue: {html.escape(descriptor)} matches</h2><img src="fig5_matches.png" style="max-width:100%">
</body></html>"""
    page_path = write_text_atomic(out / "forward.html", page)
    index = out / "index.html"
    if index.exists():
        text = index.read_text()
        link = '<p id="forward"><a href="forward.html">Forward half: enhancement (Fig. 4), feature matches ' \
               '(Table 2, Fig. 5)</a></p>'
        text = re.sub(r'<p id="forward">.*?</p>\n?', "", text)
        text = text.replace("</body>", link + "\n</body>", 1) if "</body>" in text else text + link
        write_text_atomic(index, text)
    return page_path
