"""Time of the forward-half building blocks per 640x480 frame: DCP / UDCP dehazing, UIQM / UCIQE, and
feature matching between two frames per descriptor (median over runs, after one warm-up run).

The frames are the shipped panel rendered at 2 m and 2.1 m and degraded by the underwater model.

    .venv/bin/python bench/bench_enhance.py [--runs 20] [--no-features]
"""
import argparse
import os
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from uw_sil.enhance.dcp import dehaze_dcp  # noqa: E402
from uw_sil.enhance.features import ALL_DESCRIPTORS, match_features  # noqa: E402
from uw_sil.metrics.uiqm import uciqe, uiqm  # noqa: E402

try:  # after the move to subpackages
    from uw_sil.sim.optics import degrade  # noqa: E402
    from uw_sil.sim.render import Renderer  # noqa: E402
    from uw_sil.sim.scene import facing_pose  # noqa: E402
except ImportError:
    from uw_sil.optics import degrade  # noqa: E402
    from uw_sil.render import Renderer  # noqa: E402
    from uw_sil.scene import facing_pose  # noqa: E402

PARAMS = [0.4, 0.1, 0.08, 0.06, 0.3, 0.4, 0.08]


def median_ms(fn, n):
    fn()
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


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


if __name__ == "__main__":
    main()
