"""The fit report: PNG figures and a small HTML page a person wants to read.

- ``progression.png``: the paper's Fig. 2 analogue, the real frame and the simulated frame at several
  iterations up to the optimum, each labelled (t, θ);
- ``convergence.png``: Fig. 3 analogue, best θ per iteration for each optimizer run, with the
  convergence iteration marked;
- ``residual.png``: real − fitted simulation, signed, per channel and as luminance;
- ``index.html``: the above plus a parameter table with bounds (and ground truth when known).
"""
from __future__ import annotations

import html
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .._shared.fileio import write_text_atomic
from ..sim.params import RGB_NAMES, UNITS
from ..viz import display_gain, gain_words, pyplot, save_figure

__all__ = ["progression_figure", "convergence_figure", "residual_figure", "write_report"]


def _snapshot_iterations(n_iters: int, count: int = 5) -> list[int]:
    if n_iters <= 1:
        return [0]
    its = np.unique(np.round(np.geomspace(1, n_iters, count)).astype(int) - 1)
    return [int(i) for i in its]


def _simulator(fit, frame: int):
    """x (the fit's parameter space) -> noise-free simulated image of fit frame ``frame``."""
    from ..sim.optics import PreparedRender

    rr = fit.frames[frame].render
    prep = PreparedRender(rr.rgb, rr.range, rr.depth, fog=fit.fog)
    return lambda x: prep(fit.space.to_rgb(np.asarray(x, dtype=float)))


def _closest_frame(fit) -> int:
    """The fit frame where the panel is largest (most to see in a figure)."""
    return int(np.argmax([f.coverage for f in fit.frames]))


def progression_figure(fit, frame: int = None, count: int = 5):
    """Real frame, then the simulation with the best parameters at several iterations."""
    plt = pyplot()
    frame = _closest_frame(fit) if frame is None else frame
    simulate = _simulator(fit, frame)
    o = fit.optim
    its = _snapshot_iterations(len(o.history_best_x), count)
    fig, axes = plt.subplots(1, len(its) + 1, figsize=(3.2 * (len(its) + 1), 2.9))
    real = fit.frames[frame].image.astype(np.float32) / 255.0
    g = display_gain(real)                  # (the same on the frame and every simulation of it)
    axes[0].imshow(np.clip(g * real, 0, 1))
    axes[0].set_title(f"real frame #{fit.frames[frame].index}{gain_words(g)}", fontsize=9)
    for ax, t in zip(axes[1:], its):
        x = np.asarray(o.history_best_x[t])
        sim = simulate(x)
        ax.imshow(np.clip(g * sim, 0, 1))
        ax.set_title(f"t = {t + 1}, θ = {o.history_best_f[t]:.4f}", fontsize=9)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{o.method.upper()} ({fit.space.model}): simulated frame at the best parameters so far", fontsize=10)
    fig.tight_layout()
    return fig


def convergence_figure(fits: Sequence):
    """Best θ per iteration for each run (and per evaluation count on a second axis)."""
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.8))
    for fit in fits:
        o = fit.optim
        h = np.asarray(o.history_best_f)
        label = f"{o.method} (seed {o.seed})"
        line, = ax1.plot(np.arange(1, len(h) + 1), h, label=label)
        if o.converged_iter is not None:
            ax1.axvline(o.converged_iter, color=line.get_color(), ls=":", lw=1)
        f = np.asarray(o.evaluations.f, dtype=float)
        f = np.where(np.isfinite(f), f, np.nan)
        ax2.plot(np.arange(1, len(f) + 1), np.fmax.accumulate(np.nan_to_num(f, nan=-np.inf)), label=label)
    ax1.set_xlabel("iteration t")
    ax1.set_ylabel("best θ")
    ax1.set_title("convergence (dotted: converged iteration)", fontsize=10)
    ax2.set_xlabel("objective evaluations")
    ax2.set_ylabel("best θ")
    ax2.set_xscale("log")
    ax2.set_title("best θ per evaluation", fontsize=10)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def residual_figure(fit, frame: int = None):
    """real − simulation at the fitted parameters, signed, per channel and as luminance (in 0..1 units)."""
    plt = pyplot()
    frame = _closest_frame(fit) if frame is None else frame
    simulate = _simulator(fit, frame)
    sim = simulate(fit.x_best)
    real = fit.frames[frame].image.astype(np.float32) / 255.0
    res = real - sim
    lim = max(0.05, float(np.percentile(np.abs(res), 99.5)))
    fig, axes = plt.subplots(1, 5, figsize=(17, 3.1))
    g = display_gain(real)
    axes[0].imshow(np.clip(g * sim, 0, 1))
    axes[0].set_title(f"fitted simulation, frame #{fit.frames[frame].index}{gain_words(g)}", fontsize=9)
    lum = res @ np.array([0.299, 0.587, 0.114], np.float32)
    for ax, img, name in zip(axes[1:], [lum, res[..., 0], res[..., 1], res[..., 2]], ["luminance", "R", "G", "B"]):
        im = ax.imshow(img, cmap="RdBu_r", vmin=-lim, vmax=lim)
        ax.set_title(f"real − sim, {name} (mean |·| {np.abs(img).mean():.3f})", fontsize=9)
    fig.colorbar(im, ax=axes[1:], fraction=0.02, pad=0.01)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    return fig


def _param_table(fit, truth: Optional[dict]) -> str:
    rows = []
    space = fit.space
    header = "<tr><th>parameter</th><th>unit</th><th>lower</th><th>upper</th><th>fitted</th>"
    rgb_fit = fit.params.as_vector()
    if space.model == "hsv":
        for i, n in enumerate(space.names):
            rows.append(f"<tr><td>{n}</td><td>{UNITS[n]}</td><td>{space.lower[i]:.4g}</td><td>{space.upper[i]:.4g}</td>"
                        f"<td>{fit.x_best[i]:.4f}</td>" + ("<td></td>" if truth else "") + "</tr>")
    lo_rgb = space.lower if space.model == "rgb" else [np.nan] * 7
    hi_rgb = space.upper if space.model == "rgb" else [np.nan] * 7
    for i, n in enumerate(RGB_NAMES):
        t = f"<td>{truth[n]:.4f}</td>" if truth else ""
        rows.append(f"<tr><td>{n}</td><td>{UNITS[n]}</td><td>{lo_rgb[i]:.4g}</td><td>{hi_rgb[i]:.4g}</td>"
                    f"<td>{rgb_fit[i]:.4f}</td>{t}</tr>")
    header += ("<th>ground truth</th>" if truth else "") + "</tr>"
    return "<table>" + header + "".join(rows) + "</table>"


def write_report(fits: Sequence, out_dir, truth: Optional[dict] = None, title: str = "uw_sil backward fit") -> Path:
    """Write the figures and ``index.html`` for one or more fits of the same frames (the first is the result)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fit = fits[0]
    save_figure(progression_figure(fit), out / "progression.png")
    save_figure(convergence_figure(fits), out / "convergence.png")
    save_figure(residual_figure(fit), out / "residual.png")
    s = fit.summary()
    runs = "".join(
        f"<tr><td>{f.optim.method}</td><td>{f.optim.seed}</td><td>{f.theta_start:.4f}</td><td>{f.theta_best:.4f}</td>"
        f"<td>{f.optim.n_iters}</td><td>{f.optim.n_evals}</td><td>{f.optim.converged_iter}</td>"
        f"<td>{html.escape(str(f.optim.stop_reason))}</td><td>{f.wall_time_s:.1f}</td></tr>" for f in fits)
    frames = "".join(f"<li>frame #{f['index']}: panel covers {100 * f['coverage']:.1f}%, median range "
                     f"{f['range_median_m']:.2f} m</li>" for f in s["frames"])
    skipped = "".join(f"<li>frame #{d['index']}: {html.escape(d['reason'])}</li>" for d in s["skipped_frames"])
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}img{{max-width:100%}}</style></head><body>
<h1>{html.escape(title)}</h1>
<p>θ = mean(FSIMc, HSV region-histogram similarity) over {len(fit.frames)} frame(s), channels {html.escape(fit.channels)},
histogram pixels: {fit.hist_pixels}, colour model <b>{fit.space.model}</b>, fog {html.escape(fit.fog)}. θ before: {fit.theta_start:.4f}, after: <b>{fit.theta_best:.4f}</b>.</p>
<h2>Runs</h2><table><tr><th>optimizer</th><th>seed</th><th>θ start</th><th>θ best</th><th>iterations</th>
<th>evaluations</th><th>converged at</th><th>stop</th><th>wall [s]</th></tr>{runs}</table>
<h2>Simulation during the fit (Fig. 2 analogue)</h2><img src="progression.png">
<h2>Convergence (Fig. 3 analogue)</h2><img src="convergence.png">
<h2>Residual at the optimum</h2><img src="residual.png">
<h2>Parameters</h2>{_param_table(fit, truth)}
<h2>Frames</h2><ul>{frames}</ul>{"<p>Skipped:</p><ul>" + skipped + "</ul>" if skipped else ""}
</body></html>"""
    return write_text_atomic(out / "index.html", page)
