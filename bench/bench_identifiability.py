"""Which parameters one frame cannot pin down, and how frames at several ranges fix it.

Fog (f = exp(-(rho z)^2)) and attenuation (exp(-a r)) both pull the panel towards the background
colour; at a single range a mix of the two fits nearly as well as the truth. This script maps θ over a
grid of (s, rho_f) -- s scales all three attenuations together, a = s * a_true -- for K = 1 frame
(one range) and K = 3 frames (three ranges), and writes ``identifiability.png`` with both
landscapes and the 99.5 %-of-max contour.

    .venv/bin/python bench/bench_identifiability.py [--out out/identifiability.png] [--width 320]
"""
import argparse
import os
import sys
import tempfile

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

from uw_sil.fit.backward import BackwardObjective, select_frames  # noqa: E402
from uw_sil.bags import read_samples  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.params import ParamSpace, UnderwaterParams  # noqa: E402
from uw_sil.sim.render import Renderer  # noqa: E402
from uw_sil.bags.synth import synthesize_trial  # noqa: E402
from uw_sil.viz import pyplot, save_figure  # noqa: E402

TRUTH = UnderwaterParams(a=(0.42, 0.11, 0.08), b=(0.06, 0.32, 0.42), rho_f=0.12)


def landscape(obj, scale, rho):
    X = np.tile(TRUTH.as_vector(), (scale.size * rho.size, 1))
    S, R = np.meshgrid(scale, rho, indexing="xy")
    X[:, 0:3] *= S.ravel()[:, None]
    X[:, 6] = R.ravel()
    return obj(X).reshape(S.shape)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/identifiability.png")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--grid", type=int, default=21)
    args = ap.parse_args()
    cam = CameraModel.from_fov(args.width, args.width * 3 // 4, 70.0)
    with tempfile.TemporaryDirectory() as d:
        bag = os.path.join(d, "trial.mcap")
        synthesize_trial(bag, n_frames=12, seed=0, params=TRUTH, camera=cam, start_m=3.5, end_m=1.2)
        with Renderer(camera=cam) as r:
            samples = list(read_samples(bag))
            one = select_frames(samples[6:], r, k=1).frames
            three = select_frames(samples, r, k=3, stride=4).frames
    ag = np.linspace(0.5, 1.5, args.grid)           # attenuation scale s
    rho = np.linspace(0.0, 0.3, args.grid)
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    for ax, frames, label in ((axes[0], one, "K = 1"), (axes[1], three, "K = 3")):
        th = landscape(BackwardObjective(frames, ParamSpace("rgb")), ag, rho)
        ranges = ", ".join(f"{f.range_median:.1f}" for f in frames)
        im = ax.imshow(th, origin="lower", extent=(ag[0], ag[-1], rho[0], rho[-1]), aspect="auto", cmap="magma")
        ax.contour(ag, rho, th, levels=[th.max() * 0.995], colors="cyan", linewidths=1)
        j, i = np.unravel_index(np.argmax(th), th.shape)
        ax.plot(1.0, TRUTH.rho_f, "g+", ms=14, mew=2, label="truth")
        ax.plot(ag[i], rho[j], "wx", ms=9, mew=2, label="grid max")
        ax.set_title(f"{label} (ranges {ranges} m)", fontsize=10)
        ax.set_xlabel("attenuation scale s (a = s · a_true, all channels)")
        ax.set_ylabel("rho_f [1/m]")
        ax.legend(fontsize=8, loc="upper right")
        fig.colorbar(im, ax=ax, label="θ")
        inside = th >= th.max() * 0.995
        j0 = int(np.argmin(np.abs(rho - 0.0)))
        i0 = int(np.argmax(th[j0]))
        jt, it = int(np.argmin(np.abs(rho - TRUTH.rho_f))), int(np.argmin(np.abs(ag - 1.0)))
        print(f"{label}: θ at the truth {th[jt, it]:.4f}; best explanation without fog: s={ag[i0]:.2f}, "
              f"θ {th[j0, i0]:.4f} (gap {th[jt, it] - th[j0, i0]:.4f})")
        print(f"{label}: ranges {ranges} m; grid max at s={ag[i]:.3f}, rho={rho[j]:.3f} (truth 1, "
              f"{TRUTH.rho_f}); 99.5 % region spans s {ag[inside.any(0)].min():.3f}..{ag[inside.any(0)].max():.3f}, "
              f"rho {rho[inside.any(1)].min():.3f}..{rho[inside.any(1)].max():.3f}")
    fig.suptitle("θ over attenuation (all channels scaled) and fog density, background at the truth", fontsize=11)
    fig.tight_layout()
    print(f"wrote {save_figure(fig, args.out)}")


if __name__ == "__main__":
    sys.exit(main())
