"""SIL against DCP and UDCP on synthetic trials, where the clean radiance is known (the render).

Trials: several water types (the demo's truth, clearer, more turbid, strong fog) x seeds, an approach from
4 m to 1.2 m at 640x480 with sensor noise. Each frame is enhanced by DCP, UDCP and SIL; SIL uses either the
true parameters or a "fitted" set off by a few percent (a within 5 %, b within 0.01, fog within 10 %, the
accuracy of `uw-sil fit` on such trials). Scores: PSNR and SSIM against the clean render on the panel's
pixels, UIQM and UCIQE (no reference) of the whole frame.

    PYOPENGL_PLATFORM=osmesa .venv/bin/python bench/bench_enhance_quality.py [--frames 8] [--seeds 2]

Last line: ``quality: SIL beat DCP and UDCP (PSNR and SSIM) on k/n trials, f/F frames; ...``.
"""
import argparse
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

from uw_sil.bags.synth import SensorNoise, add_sensor_noise, approach_trajectory  # noqa: E402
from uw_sil.enhance.sil import Enhancer  # noqa: E402
from uw_sil.metrics.fidelity import psnr, ssim  # noqa: E402
from uw_sil.metrics.uiqm import uciqe, uiqm  # noqa: E402
from uw_sil.sim.params import UnderwaterParams  # noqa: E402
from uw_sil.sim.simcam import SimCamera  # noqa: E402

WATERS = {
    "demo": UnderwaterParams(a=(0.42, 0.11, 0.08), b=(0.06, 0.32, 0.42), rho_f=0.08),
    "clear": UnderwaterParams(a=(0.30, 0.06, 0.05), b=(0.03, 0.20, 0.35), rho_f=0.03),
    "turbid": UnderwaterParams(a=(0.55, 0.25, 0.22), b=(0.12, 0.38, 0.35), rho_f=0.12),
    "foggy": UnderwaterParams(a=(0.40, 0.10, 0.09), b=(0.08, 0.30, 0.40), rho_f=0.20),
}
METHODS = ("raw", "dcp", "udcp", "sil")


def fitted_like(p: UnderwaterParams, rng) -> UnderwaterParams:
    a = np.array(p.a) * (1 + rng.uniform(-0.05, 0.05, 3))
    b = np.clip(np.array(p.b) + rng.uniform(-0.01, 0.01, 3), 0, 1)
    return UnderwaterParams(tuple(a), tuple(b), p.rho_f * (1 + rng.uniform(-0.1, 0.1)))


def trial(name, truth, seed, n_frames, fitted):
    rng = np.random.default_rng(seed)
    model = fitted_like(truth, rng) if fitted else truth
    e = Enhancer(model)
    rows = []
    with SimCamera(truth) as sim:
        for T in approach_trajectory(n_frames, 4.0, 1.2, rng):
            f = sim.render(T)
            img = add_sensor_noise(f.image, SensorNoise(), rng)
            obj = f.render.labels > 0
            for m in METHODS:
                out = img if m == "raw" else e.enhance(img, m, geometry=f.render).image
                rows.append({"trial": name, "seed": seed, "range": float(np.linalg.norm(T[:3, 3])), "method": m,
                             "psnr": psnr(out, f.render.rgb, obj), "ssim": ssim(out, f.render.rgb, obj),
                             "uiqm": uiqm(out), "uciqe": uciqe(out)})
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args()
    all_rows, trials = [], []
    for name, truth in WATERS.items():
        for seed in range(args.seeds):
            for fitted in (False, True):
                label = f"{name}/s{seed}/{'fitted' if fitted else 'truth'}"
                rows = trial(label, truth, seed, args.frames, fitted)
                all_rows += rows
                trials.append(label)
                mean = {m: {k: np.mean([r[k] for r in rows if r["method"] == m])
                            for k in ("psnr", "ssim", "uiqm", "uciqe")} for m in METHODS}
                print(f"{label:22s} " + "  ".join(f"{m}: {v['psnr']:5.2f} dB {v['ssim']:.3f} "
                                                  f"uiqm {v['uiqm']:.2f} uciqe {v['uciqe']:.3f}"
                                                  for m, v in mean.items()), flush=True)
    # per frame margins of SIL over the better of DCP and UDCP
    frames = {}
    for r in all_rows:
        frames.setdefault((r["trial"], r["range"]), {})[r["method"]] = r
    dp, ds, won_frames = [], [], 0
    won_trials = {t: True for t in trials}
    for (t, _), d in frames.items():
        mp = d["sil"]["psnr"] - max(d["dcp"]["psnr"], d["udcp"]["psnr"])
        ms = d["sil"]["ssim"] - max(d["dcp"]["ssim"], d["udcp"]["ssim"])
        dp.append(mp)
        ds.append(ms)
        if mp > 0 and ms > 0:
            won_frames += 1
        else:
            won_trials[t] = False
    means = {m: {k: np.mean([r[k] for r in all_rows if r["method"] == m]) for k in ("psnr", "ssim", "uiqm", "uciqe")}
             for m in METHODS}
    print("\nmean over all frames: " + "; ".join(
        f"{m} PSNR {v['psnr']:.2f} dB SSIM {v['ssim']:.3f} UIQM {v['uiqm']:.2f} UCIQE {v['uciqe']:.3f}"
        for m, v in means.items()))
    print(f"quality: SIL beat DCP and UDCP (PSNR and SSIM on the panel) on {sum(won_trials.values())}/{len(trials)} "
          f"trials, {won_frames}/{len(frames)} frames; margin over the better baseline: PSNR min {min(dp):.1f} dB, "
          f"mean {np.mean(dp):.1f} dB; SSIM min {min(ds):.3f}, mean {np.mean(ds):.3f}")


if __name__ == "__main__":
    main()
