"""Report of a mismatch diagnosis: PNG figures and an HTML page.

- ``residuals.png``: every frame as recorded, as the fitted base model simulates it, and the residual
  (luminance, signed) overlaid on the recording; held-out frames marked;
- ``signatures.png``: the residual against range (object log-ratio and additive bias per frame), against
  the image radius (water log-ratio profiles), against intensity (residual per simulated grey level),
  and against spatial frequency (power-spectrum ratio recording/simulation per frame);
- ``models.png``: for held-out frames, the recording next to the base simulation, the simulation of the final
  (extended) model and what the final model leaves over (luminance, signed, on the base model's scale);
- ``heldout.png``: held-out θ of the base model and of each refitted candidate (per frame and mean, with
  the acceptance margin);
- ``index.html``: verdict, candidates, where the mismatch is, signature numbers, timing.
"""
from __future__ import annotations

import html
import json
import textwrap
from pathlib import Path

import numpy as np

from .._shared.fileio import write_text_atomic
from ..viz import display_gain, gain_words, pyplot, save_figure

__all__ = ["write_diagnosis_report"]


def _lum(img):
    return np.asarray(img, np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)


def residual_figure(diag):
    plt = pyplot()
    F = diag.figures
    rfs, sims, res = F["rframes"], F["sims"], F["res"]
    n = len(rfs)
    fig, axes = plt.subplots(n, 3, figsize=(10, 2.5 * n), squeeze=False)
    lim = max(5.0, float(np.percentile(np.abs(np.concatenate([_lum(r).ravel() for r in res])), 99)))
    for ax, rf, s, r in zip(axes, rfs, sims, res):
        fr = rf.frame
        tag = " (held out)" if fr.role == "heldout" else ""
        g = display_gain(rf.image / 255.0)          # (the same on the recording and its simulation)
        ax[0].imshow(np.clip(g * rf.image / 255.0, 0, 1))
        ax[0].set_title(f"recording #{fr.index}, {fr.range_median:.2f} m{tag}{gain_words(g)}", fontsize=8)
        ax[1].imshow(np.clip(g * s, 0, 1))
        ax[1].set_title(f"base model (fitted){gain_words(g)}", fontsize=8)
        ax[2].imshow(np.clip(g * _lum(rf.image) / 255.0, 0, 1), cmap="gray")
        L = _lum(r)
        im = ax[2].imshow(np.ma.masked_where(np.abs(L) < 0.1 * lim, L), cmap="coolwarm", vmin=-lim, vmax=lim,
                          alpha=0.8)
        ax[2].set_title("residual real − sim (grey levels)", fontsize=8)
        fig.colorbar(im, ax=ax[2], fraction=0.035, pad=0.02)
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
    fig.tight_layout()
    return fig


def signature_figure(diag):
    plt = pyplot()
    F = diag.figures
    sigs = F["sigs"]
    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    # residual vs range
    ax = axes[0, 0]
    al = sigs.get("artificial_light")
    if al is not None and al.plot.get("levels"):
        r, lv = al.plot["levels"]
        ax.plot(r, lv, "o-", label="object log-ratio real/sim (mean)")
    bc = sigs.get("backscatter_coefficient")
    if bc is not None and bc.plot.get("additive"):
        r, add = bc.plot["additive"]
        add = np.asarray(add)
        ax2 = ax.twinx()
        for c, col in enumerate("rgb"):
            ax2.plot(r, add[:, c], "s--", color=col, alpha=0.6, label=f"additive object bias {col} (DN)")
        ax2.set_ylabel("additive bias on the object minus water (DN)")
        ax2.legend(fontsize=7, loc="lower right")
    fs = sigs.get("forward_scatter")
    if fs is not None and fs.plot.get("blur"):
        r, b = fs.plot["blur"]
        ax.plot(r, np.asarray(b) / 10.0, "^:", color="k", label="best blur width / 10 (px)")
    ax.set_xlabel("range (m)")
    ax.set_title("residual vs range", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    # residual vs radius
    ax = axes[0, 1]
    vg = sigs.get("vignetting")
    if vg is not None and vg.plot.get("radial"):
        for k, cen, med in vg.plot["radial"]:
            ax.plot(cen, med, "-", alpha=0.7, label=f"frame {k}")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("radius (tan of field angle)")
    ax.set_ylabel("water log-ratio real/sim")
    ax.set_title("residual vs radius (open water)", fontsize=9)
    ax.legend(fontsize=6)
    # residual vs intensity
    ax = axes[1, 0]
    cr = sigs.get("camera_response")
    if cr is not None and cr.plot.get("curves"):
        for c, cen, med in cr.plot["curves"]:
            ax.plot(cen, med, "o-", color="rgb"[c], label=f"channel {'rgb'[c]}")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("simulated grey level")
    ax.set_ylabel("median residual (DN)")
    ax.set_title("residual vs intensity", fontsize=9)
    ax.legend(fontsize=7)
    # spatial frequency
    ax = axes[1, 1]
    if fs is not None and fs.plot.get("spectra"):
        cmap = plt.get_cmap("viridis")
        rs = [s[0] for s in fs.plot["spectra"]]
        lo, hi = min(rs), max(rs) + 1e-6
        for rng, f, ratio in fs.plot["spectra"]:
            ax.semilogy(f, np.maximum(ratio, 1e-3), color=cmap((rng - lo) / (hi - lo)), label=f"{rng:.1f} m")
    ax.axhline(1, color="k", lw=0.5)
    ax.set_xlabel("spatial frequency (cycles/pixel, full resolution)")
    ax.set_ylabel("power ratio real/sim")
    ax.set_title("residual vs spatial frequency (object window)", fontsize=9)
    ax.legend(fontsize=6)
    fig.tight_layout()
    return fig


def models_figure(diag):
    plt = pyplot()
    F = diag.figures
    held = F["held"]
    key = F["final_key"]
    from .residuals import base_sim

    rows = held[:3]
    fig, axes = plt.subplots(len(rows), 4, figsize=(13.5, 2.6 * len(rows)), squeeze=False)
    ext = None
    if key is not None:
        # the final model on the frames it was scored on (their geometry corrected where it absorbed a pose error)
        final_model, final_x, final_rows = F["final"]
        ext = final_model.like(final_rows[:len(rows)])
    for k, (ax, rf) in enumerate(zip(axes, rows)):
        g = display_gain(rf.image / 255.0)          # (the same on the recording and its simulations)
        ax[0].imshow(np.clip(g * rf.image / 255.0, 0, 1))
        ax[0].set_title(f"recording #{rf.frame.index} (held out, {rf.frame.range_median:.2f} m){gain_words(g)}",
                        fontsize=8)
        sb = base_sim(rf, F["base_x"], F["fog"])
        ax[1].imshow(np.clip(g * sb, 0, 1))
        ax[1].set_title(f"base model{gain_words(g)}", fontsize=8)
        se = sb
        if ext is not None:
            se = ext.simulate(k, final_x[None])[0]
            ax[2].imshow(np.clip(g * se, 0, 1))
            # (wrapped: a model of three or four effects ran into the next column's title)
            ax[2].set_title("\n".join(textwrap.wrap(f"extended model: {key}{gain_words(g)}", 56)), fontsize=8)
        else:
            ax[2].text(0.5, 0.5, "no effect accepted", ha="center", va="center")
        # what the final model leaves over, on the base model's colour scale (lighter: less left)
        rb, re_ = _lum(rf.image - 255.0 * sb), _lum(rf.image - 255.0 * se)
        lim = max(5.0, float(np.percentile(np.abs(rb), 99)))
        im = ax[3].imshow(re_, cmap="coolwarm", vmin=-lim, vmax=lim)
        rms = [float(np.sqrt(np.mean(r * r))) for r in (rb, re_)]
        ax[3].set_title(f"left over: real − {'extended' if ext is not None else 'base'} (rms {rms[1]:.1f}; base "
                        f"{rms[0]:.1f} DN)", fontsize=8)
        fig.colorbar(im, ax=ax[3], fraction=0.035, pad=0.02)
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
    fig.tight_layout()
    return fig


def heldout_figure(diag):
    plt = pyplot()
    F = diag.figures
    base = F["base_held_pf"]
    fits = F["fits"]
    names = [n for n in fits if n != "base"]          # the selection path: base + e1, base + e1 + e2, ...
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.8))
    ax = axes[0]
    x = np.arange(len(base))
    ax.plot(x, base, "ko-", label=f"base ({base.mean():.4f})")
    for n in names:
        ax.plot(x, fits[n]["held_pf"], "o--", label=f"{n} ({fits[n]['held_pf'].mean():.4f})")
    ax.set_xticks(x)
    ax.set_xticklabels([f"#{rf.frame.index}\n{rf.frame.range_median:.1f} m" for rf in F["held"]], fontsize=7)
    ax.set_ylabel("held-out θ")
    ax.set_title("held-out θ per frame", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1]
    vals = [base.mean()] + [fits[n]["held_pf"].mean() for n in names]
    labels = ["base"] + names
    colors = ["grey"] + ["tab:green" if n == F["final_key"] else "tab:blue" for n in names]
    ax.bar(range(len(vals)), vals, color=colors)
    ax.axhline(base.mean() + diag.noise["margin"], color="r", ls="--", lw=0.8, label="base + acceptance margin")
    rep = (diag.base.get("theta_report"), diag.final.get("theta_report"))
    if rep[1] is not None:
        # the report frames: what the base and the final model score where no fit and no choice looked
        final_at = labels.index(F["final_key"]) if F["final_key"] in labels else 0
        ax.plot([0, final_at], rep, "kD", ms=6, label=f"report frames ({rep[0]:.4f} -> {rep[1]:.4f})")
    shown = vals + [v for v in rep if v is not None]
    lo = min(shown) - 0.02
    ax.set_ylim(max(0.0, lo), min(1.0, max(shown) + 0.02))
    ax.set_xticks(range(len(vals)))
    ax.set_xticklabels(labels, rotation=20, fontsize=7, ha="right")
    ax.set_title("held-out θ along the selection (green: final model)", fontsize=9)
    ax.legend(fontsize=7)
    # the other held-out criterion: the least-squares fits' mean squared residual, pooled over the frames
    ax = axes[2]
    E = [float(np.mean(fits[n]["held_E"])) if fits[n].get("held_E") is not None else np.nan
         for n in ["base"] + names]
    ax.bar(range(len(E)), E, color=colors)
    ax.set_xticks(range(len(E)))
    ax.set_xticklabels(labels, rotation=20, fontsize=7, ha="right")
    ax.set_ylabel("grey levels²")
    ax.set_title("held-out residual of the least-squares fits (lower is better)", fontsize=9)
    fig.tight_layout()
    return fig


def _table(rows, header):
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    return str(v)


def write_diagnosis_report(diag, out_dir, title: str = "uw_sil mismatch diagnosis") -> Path:
    """Write the figures and ``index.html`` into ``out_dir``; returns the page's path."""
    from .diagnose import outcome_words
    from .judges.sensor_noise import camera_noise_words

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = {"residuals.png": residual_figure, "signatures.png": signature_figure, "models.png": models_figure,
            "heldout.png": heldout_figure}
    for name, fn in figs.items():
        save_figure(fn(diag), out / name)
    d = diag.to_json()
    parts = [f"<h1>{html.escape(title)}</h1>", f"<p>source: {html.escape(diag.source)}</p>", "<h2>Verdict</h2>"]
    if d["verdict"]:
        parts.append("<ul>" + "".join(f"<li><b>{html.escape(v['effect'])}</b> (confidence {v['confidence']:.2f}): "
                                      f"{html.escape(v['explanation'])}</li>" for v in d["verdict"]) + "</ul>")
    else:
        parts.append(f"<p><b>none</b>: no effect raised held-out θ beyond the fit's noise (margin "
                     f"{d['noise']['margin']:.4f}).</p>")
    if d.get("undecided"):
        parts.append("<p>Undecided, not named: evidence the final model's effects explain as well (frames that move "
                     "them apart would decide)</p><ul>" + "".join(f"<li>{html.escape(u['explanation'])}</li>"
                                                                 for u in d["undecided"]) + "</ul>")
    parts.append(f"<p>held-out θ: base {d['base']['theta_heldout']:.4f} → final {d['final']['theta_heldout']:.4f} "
                 f"(train θ of the base fit {d['base']['theta_train']:.4f})</p>")
    if d["final"].get("theta_heldout_simulated") is not None:
        parts.append(f"<p>held-out θ as <code>sim_camera</code> renders the models (at the recording's resolution, "
                     f"their noise and particles drawn): base {d['base']['theta_heldout_simulated']:.4f} → final "
                     f"{d['final']['theta_heldout_simulated']:.4f}</p>")
    noise_words = camera_noise_words(d["final"].get("camera_noise"))
    if noise_words:
        parts.append(f"<p>camera noise <code>sim_camera</code> draws: {html.escape(noise_words)}</p>")
    if d["final"].get("theta_report") is not None:
        rep = [f["index"] for f in d["frames"] if f["role"] == "report"]
        parts.append(f"<p>on the report frames {rep}, which no fit and no choice saw: θ base "
                     f"{d['base']['theta_report']:.4f} → final {d['final']['theta_report']:.4f}</p>")
    parts.append('<img src="heldout.png" width="900">')
    if d["base"].get("doubts"):
        parts.append("<p>doubt about the base fit: " + html.escape("; ".join(d["base"]["doubts"])) + "</p>")
    parts.append("<h2>Selection, step by step (every effect refitted, held-out frames decide)</h2>")
    parts.append(_table([(s["round"], s["model"], s["theta_heldout"], ", ".join(s["tried"]), s["chosen"] or "—",
                          s["time_s"]) for s in d.get("selection", [])],
                        ["round", "model", "θ held-out", "effects refitted", "chosen", "s"]))
    parts.append("<h2>Candidates (refitted jointly with the round's model, judged on held-out frames)</h2>")
    parts.append(_table([(c.get("round", 1), c.get("model", "base"), c["effect"], c["theta_train"], c["theta_heldout"],
                          c["delta_heldout"], c.get("margin", 0.0), "yes" if c.get("accepted") else "no",
                          "" if c.get("elimination") else outcome_words(c, d.get("selection", [])).strip())
                         for c in d["candidates"]],
                        ["round", "model", "+ effect", "θ train", "θ held-out", "Δ held-out", "margin", "beats margin",
                         "outcome"]))
    parts.append('<h2>Base vs extended model (held-out frames)</h2><img src="models.png" width="900">')
    parts.append("<h2>Where the mismatch is</h2>")
    parts.append(_table([(r["kind"], r["name"], r["pixels"], r["rms"], r["mean"], r["share"])
                         for r in d["mismatch"]["regions"]],
                        ["kind", "region", "pixels", "rms (DN)", "mean r,g,b (DN)", "share of excess"]))
    parts.append('<img src="residuals.png" width="900">')
    parts.append("<h2>Signatures</h2>")
    parts.append(_table([(e, s["score"], s.get("explained_share"), s.get("order_score"), s["judged"],
                          json.dumps(s["stats"])[:300]) for e, s in d["signatures"].items()],
                        ["effect", "signature score", "explained share", "order score", "judged", "numbers"]))
    parts.append('<img src="signatures.png" width="900">')
    parts.append("<h2>Timing</h2>" + _table([(k, v) for k, v in d["timing"].items()], ["step", "s"]))
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>" + html.escape(title) +
            "</title><style>body{font-family:sans-serif;max-width:1000px;margin:auto}table{border-collapse:collapse;"
            "font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px}</style></head><body>" + "\n".join(parts) +
            "</body></html>")
    write_text_atomic(out / "index.html", page)
    return out / "index.html"
