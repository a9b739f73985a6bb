"""Time of the forward-half building blocks per 640x480 frame: DCP / UDCP dehazing, UIQM / UCIQE, and
feature matching between two frames per descriptor (median over runs, after one warm-up run); then SIL
against DCP and UDCP on the same frames in one run, on one thread.

The frames are the shipped panel rendered at 2 m and 2.1 m and degraded by the underwater model; the SIL
comparison uses a noisy synthetic approach (4 m to 1.2 m) with the render of each frame given.

    .venv/bin/python bench/bench_enhance.py [--runs 20] [--no-features] [--sil-frames 10]

Last line: ``enhance 640x480, 1 thread: sil=... ms (...) dcp=... ms udcp=... ms dcp/sil=<ratio>x``.
"""
import argparse
import os
import sys

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from uw_sil.enhance.dcp import dehaze_dcp  # noqa: E402
from uw_sil.enhance.features import ALL_DESCRIPTORS, match_features  # noqa: E402
from uw_sil.metrics.uiqm import uciqe, uiqm  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_core import median_ms  # noqa: E402  -- warm-up run, then the median of n

from uw_sil.sim.optics import degrade  # noqa: E402
from uw_sil.sim.render import Renderer  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402

PARAMS = [0.4, 0.1, 0.08, 0.06, 0.3, 0.4, 0.08]


def frames():
    out = []
    with Renderer() as r:
        for pose in (facing_pose(2.0), facing_pose(2.1, x=0.1, yaw=0.1)):
            rr = r.render(pose)
            out.append(degrade(rr.rgb, rr.range, rr.depth, PARAMS).astype(np.float32))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--no-features", action="store_true")
    ap.add_argument("--sil-frames", type=int, default=10, help="frames of the SIL vs DCP comparison")
    args = ap.parse_args()
    f1, f2 = frames()
    assert f1.shape == (480, 640, 3), f1.shape
    u8 = np.rint(f1 * 255).astype(np.uint8)
    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; 640x480, median of {args.runs} runs")
    rows = [
        ("dehaze_dcp variant=dcp (float32)", lambda: dehaze_dcp(f1)),
        ("dehaze_dcp variant=udcp (float32)", lambda: dehaze_dcp(f1, variant="udcp")),
        ("dehaze_dcp variant=dcp (uint8)", lambda: dehaze_dcp(u8)),
        ("uiqm", lambda: uiqm(f1)),
        ("uciqe", lambda: uciqe(f1)),
    ]
    if not args.no_features:
        rows += [(f"match_features {d} (two frames)", lambda d=d: match_features(f1, f2, d))
                 for d in ALL_DESCRIPTORS]
    for name, fn in rows:
        runs = args.runs if not name.startswith("match") else max(3, args.runs // 4)
        print(f"{name:40s} {median_ms(fn, runs):8.1f} ms")
    sil_vs_dcp(args.sil_frames, max(3, args.runs // 4))


def sil_vs_dcp(n_frames: int, runs: int):
    """Per-frame time of SIL (as the enhancer node runs it: depth + mask + camera of a new geometry each
    frame; and with the geometry's gain map cached), DCP and UDCP on the same uint8 frames, one thread."""
    from uw_sil.bags.synth import DEFAULT_TRUTH, SensorNoise, add_sensor_noise, approach_trajectory
    from uw_sil.enhance.sil import Enhancer
    from uw_sil.sim.simcam import SimCamera

    rng = np.random.default_rng(0)
    with SimCamera(DEFAULT_TRUTH) as sim:
        data = []
        for T in approach_trajectory(n_frames, 4.0, 1.2, rng):
            f = sim.render(T)
            data.append((add_sensor_noise(f.image, SensorNoise(), rng), f.render, sim.camera))
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        e = Enhancer(DEFAULT_TRUTH)
        per = {"sil": [], "sil_cached": [], "dcp": [], "udcp": []}
        for img, rr, cam in data:
            per["sil"].append(median_ms(lambda: e.enhance(img, depth=rr.depth, mask=rr.labels, camera=cam), runs))
            per["sil_cached"].append(median_ms(lambda: e.enhance(img, geometry=rr, geometry_key=id(rr)), runs))
            per["dcp"].append(median_ms(lambda: e.enhance(img, "dcp"), runs))
            per["udcp"].append(median_ms(lambda: e.enhance(img, "udcp"), runs))
    finally:
        cv2.setNumThreads(threads)
    cover = [float((rr.labels > 0).mean()) for _, rr, _ in data]
    print(f"\nSIL vs DCP/UDCP on {n_frames} frames of an approach (panel covers {100 * min(cover):.0f}-"
          f"{100 * max(cover):.0f}% of the frame), uint8 640x480, 1 thread, median of {runs} runs per frame:")
    for k, v in per.items():
        print(f"  {k:10s} mean {np.mean(v):7.2f} ms  max {np.max(v):7.2f} ms")
    sil, dcp, udcp = (float(np.mean(per[k])) for k in ("sil", "dcp", "udcp"))
    print(f"enhance 640x480, 1 thread: sil={sil:.2f} ms (cached gain {np.mean(per['sil_cached']):.2f} ms, "
          f"worst frame {np.max(per['sil']):.2f} ms) dcp={dcp:.1f} ms udcp={udcp:.1f} ms dcp/sil={dcp / sil:.1f}x")


if __name__ == "__main__":
    main()
