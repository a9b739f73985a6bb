"""Effects of the extended underwater model: subtlety of the presets (1 - FSIMc) and evaluation time.

    python bench/bench_effects.py [--size 640x480] [--fsim] [--time] [--jacobian] [--effects a,b]

--fsim: for each effect and severity, 1 - FSIMc between frames with and without it, on three frames of an
approach (4.0, 2.5, 1.4 m, with yaw/pitch), "clean" (float frames, no camera noise) and "trial" (both
frames with the synthetic trial's sensor noise, the same realization, 8-bit), plus the mean absolute
change in grey levels. --time: per-frame degrade (incl. per-render preparation) and per-candidate time of
the prepared evaluator (N = 20, steady state) for each effect alone (strong), at the given size.
--jacobian: time per column of a forward-difference Jacobian (one batch of the 7 base + the effect's parameters,
each moved by one step, as the diagnosis' least-squares fits evaluate it) for each effect alone (strong), with
the effects' per-render caches and without them (``cache_entries = 0``) in the same run; last line: the ratio
for the vehicle lamps.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from uw_sil.bags.synth import DEFAULT_TRUTH, SensorNoise, add_sensor_noise  # noqa: E402
from uw_sil.metrics.fsim import fsim  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.effects import EFFECTS  # noqa: E402
from uw_sil.sim.model import UnderwaterModel  # noqa: E402
from uw_sil.sim.render import Renderer  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402

POSES = [facing_pose(4.0, x=0.05, yaw=0.1, pitch=0.05), facing_pose(2.5, yaw=-0.15, pitch=0.08),
         facing_pose(1.4, x=-0.05, yaw=0.08)]


def table_fsim(renders, cam, names):
    base = [UnderwaterModel(DEFAULT_TRUTH).degrade(rr, cam) for _, rr in renders]

    def noisy(img, k):
        return add_sensor_noise(img, SensorNoise(), np.random.default_rng(100 + k)).astype(np.float64)

    print(f"{'effect':25s} {'severity':8s} {'clean (4.0/2.5/1.4 m)':>28s} {'mean':>6s}   "
          f"{'trial (4.0/2.5/1.4 m)':>28s} {'mean':>6s}  {'|dI| DN':>7s}")
    for name in names:
        for sev in ("mild", "strong"):
            m = UnderwaterModel(DEFAULT_TRUTH, {name: sev})
            clean, trial, dn = [], [], []
            for k, ((T, rr), b0) in enumerate(zip(renders, base)):
                img = m.degrade(rr, cam, rng=np.random.default_rng(k + 1), pose=T)
                clean.append(1 - fsim(b0 * 255, img * 255).fsimc)
                trial.append(1 - fsim(noisy(b0, k), noisy(img, k)).fsimc)
                dn.append(np.abs(img - b0).mean() * 255)
            print(f"{name:25s} {sev:8s} {' '.join(f'{v:8.4f}' for v in clean):>28s} {np.mean(clean):6.4f}   "
                  f"{' '.join(f'{v:8.4f}' for v in trial):>28s} {np.mean(trial):6.4f}  {np.mean(dn):7.1f}", flush=True)


def table_time(renders, cam, names, n=20, repeat=3):
    from uw_sil.sim.optics import PreparedRender

    T, rr = renders[1]
    rng = np.random.default_rng(0)
    base = np.tile(DEFAULT_TRUTH.as_vector(), (n, 1))
    base[:, :3] *= rng.uniform(0.9, 1.1, (n, 3))
    out = np.empty((n, cam.height, cam.width, 3), np.float32)
    ref = PreparedRender(rr.rgb, rr.range, rr.depth)
    ref(base, out=out)
    t = time.perf_counter()
    for _ in range(repeat):
        ref(base, out=out)
    print(f"reference: uw_sil.sim.optics.PreparedRender {(time.perf_counter() - t) / repeat / n * 1e3:.2f} ms/candidate")
    print(f"{'effects (strong)':25s} {'degrade ms':>11s} {'prepared ms/candidate':>22s}")
    for name in [None] + names:
        effects = {} if name is None else {name: "strong"}
        m = UnderwaterModel(DEFAULT_TRUTH, effects)
        m.degrade(rr, cam, pose=T)                                    # warm caches (textures, kernels)
        t = time.perf_counter()
        for _ in range(repeat):
            m.degrade(rr, cam, rng=np.random.default_rng(1), pose=T)
        t_deg = (time.perf_counter() - t) / repeat
        pm = m.prepare(rr, cam, pose=T)
        ev = np.tile(m.effect_vector(), (n, 1))
        pm(base, ev, out=out)
        t = time.perf_counter()
        for _ in range(repeat):
            pm(base, ev, out=out)
        t_prep = (time.perf_counter() - t) / repeat / n
        print(f"{name or '(base only)':25s} {t_deg * 1e3:11.1f} {t_prep * 1e3:22.2f}", flush=True)
    print("(geometry effects: the prepared evaluator caches the corrected geometry per parameter set; when a fit\n"
          " varies them, each candidate costs about one degrade)")


def table_jacobian(renders, cam, names, repeat=3):
    T, rr = renders[1]
    print(f"{'effects (strong)':25s} {'columns':>7s} {'no cache ms/col':>16s} {'cached ms/col':>14s} {'ratio':>6s}")
    ratios = {}
    for name in names:
        e = EFFECTS[name]
        if not hasattr(type(e), "cache_entries"):
            continue
        m = UnderwaterModel(DEFAULT_TRUTH, {name: "strong"})
        x = np.concatenate([DEFAULT_TRUTH.as_vector(), m.effect_vector()])
        h = 2e-3 * np.maximum(1.0, np.abs(x))
        X = x[None] + np.diag(h)
        times = {}
        for entries in (0, type(e).cache_entries):
            e.cache_entries = entries
            try:
                best = np.inf
                for _ in range(repeat):
                    pm = m.prepare(rr, cam, pose=T)            # a fresh render state: empty caches
                    t = time.perf_counter()
                    pm(x[None, :7], x[None, 7:])                # f(x), evaluated just before the Jacobian
                    pm(X[:, :7], X[:, 7:])
                    best = min(best, time.perf_counter() - t)
                times[entries] = best / len(X)
            finally:
                del e.cache_entries                             # back to the class's value
        ratios[name] = times[0] / times[type(e).cache_entries]
        print(f"{name:25s} {len(X):7d} {times[0] * 1e3:16.2f} {times[type(e).cache_entries] * 1e3:14.2f} "
              f"{ratios[name]:6.2f}", flush=True)
    if "artificial_light" in ratios:
        print(f"jacobian: artificial_light no-cache/cached = {ratios['artificial_light']:.2f}x per column")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--fsim", action="store_true")
    ap.add_argument("--time", action="store_true")
    ap.add_argument("--jacobian", action="store_true")
    ap.add_argument("--effects", default=",".join(EFFECTS))
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    names = [n for n in args.effects.split(",") if n]
    with Renderer(camera=CameraModel.from_fov(w, h)) as r:
        renders = [(T, r.render(T)) for T in POSES]
        print(f"# {w}x{h}, truth {DEFAULT_TRUTH.as_dict()}")
        if args.fsim or not (args.time or args.jacobian):
            table_fsim(renders, r.camera, names)
        if args.time:
            table_time(renders, r.camera, names)
        if args.jacobian:
            table_jacobian(renders, r.camera, names)


if __name__ == "__main__":
    main()
