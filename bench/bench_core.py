"""Render and degrade time per 640x480 frame: one render, then the underwater model for one parameter
set and for N = 20 sets at once (the optimizer's inner loop), with and without a reused output buffer.

    .venv/bin/python bench/bench_core.py [--frames 50]
"""
import argparse
import os
import sys
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

from uw_sil.sim.optics import PreparedRender, degrade  # noqa: E402
from uw_sil.sim.render import Renderer  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402


def median_ms(fn, n):
    fn()
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=50)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    with Renderer() as r:
        pose = facing_pose(1.5, yaw=0.2)
        render_ms = median_ms(lambda: r.render(pose), args.frames)
        rr = r.render(pose)
    p1 = np.array([0.42, 0.11, 0.08, 0.06, 0.32, 0.42, 0.08])
    P = np.column_stack([rng.uniform(0, 0.6, (20, 3)), rng.uniform(0, 1, (20, 3)), rng.uniform(0, 0.3, 20)])
    prep = PreparedRender(rr.rgb, rr.range, rr.depth)
    buf = np.empty((20,) + rr.rgb.shape, np.float32)
    one_full = median_ms(lambda: degrade(rr.rgb, rr.range, rr.depth, p1), args.frames)
    one = median_ms(lambda: prep(p1, out=buf[0]), args.frames)
    batch = median_ms(lambda: prep(P), 10)
    batch_buf = median_ms(lambda: prep(P, out=buf), 10)
    print(f"render (colour + depth/labels), 640x480:        {render_ms:7.1f} ms/frame   (panel covers "
          f"{100 * (rr.labels == 1).mean():.0f} %)")
    print(f"degrade, one set, degrade() incl. set-up:       {one_full:7.2f} ms")
    print(f"degrade, one set, PreparedRender, reused out:   {one:7.2f} ms")
    print(f"degrade, N=20 sets, new output array:           {batch:7.2f} ms  ({batch / 20:.2f} ms/set)")
    print(f"degrade, N=20 sets, reused output buffer:       {batch_buf:7.2f} ms  ({batch_buf / 20:.2f} ms/set)")
    print(f"batched N=20 vs 20 x single: {batch_buf / (20 * one):.2f}x")


if __name__ == "__main__":
    sys.exit(main())
