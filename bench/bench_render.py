"""Benchmark of uw_sil.sim.render: time per 640x480 frame (the GL pass or passes + post-processing).

Run standalone::

    .venv/bin/python bench/bench_render.py [--frames 100] [--width 640 --height 480] [--seafloor]

Prints the model load and context creation time, the first render (shader compilation and
model upload), the median / p90 time per frame over ``--frames`` poses around the panel,
the split between the GL pass (one under OSMesa: the ids in the colour pass's alpha; else colour and
SEG) and numpy post-processing, the resident memory
before and after the loop, and the median of a geometry-only render (``colour=False``).
Last line: ``render: frame_ms=X geometry_ms=Y fps=Z``.
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np


def rss_mb() -> float:
    """Resident set size of this process in MiB (Linux)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--hfov", type=float, default=70.0, help="horizontal field of view, degrees")
    ap.add_argument("--shading", default="lambert", choices=("lambert", "flat"))
    ap.add_argument("--seafloor", action="store_true", help="add the textured seafloor plane")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    from uw_sil.sim.camera import CameraModel
    from uw_sil.sim.render import Renderer, _pyrender
    from uw_sil.sim.scene import add_seafloor, facing_pose, load_model

    t_import = time.perf_counter() - t0
    rss_start = rss_mb()

    t0 = time.perf_counter()
    model = load_model()
    if args.seafloor:
        model = add_seafloor(model)
    t_load = time.perf_counter() - t0

    camera = CameraModel.from_fov(args.width, args.height, hfov_deg=args.hfov)
    t0 = time.perf_counter()
    _pyrender()  # imports pyrender + PyOpenGL for OSMesa and applies the context-key fix
    t_gl_import = time.perf_counter() - t0
    t0 = time.perf_counter()
    renderer = Renderer(model, camera=camera, shading=args.shading)
    t_create = time.perf_counter() - t0

    poses = [facing_pose(1.0 + 1.5 * (0.5 + 0.5 * math.sin(0.37 * i)), x=0.1 * math.sin(0.23 * i),
                         y=0.05 * math.cos(0.31 * i), yaw=0.5 * math.sin(0.11 * i), pitch=0.3 * math.sin(0.17 * i),
                         roll=0.1 * math.sin(0.07 * i)) for i in range(args.frames)]

    t0 = time.perf_counter()
    first = renderer.render(poses[0])
    t_first = time.perf_counter() - t0
    rss_before = rss_mb()

    # Split of one frame: the GL pass(es) (pyrender) and numpy post-processing.
    off, scene = renderer._offscreen, renderer._scene
    t_frame, t_color, t_seg = [], [], []
    for T in poses:
        t0 = time.perf_counter()
        renderer.render(T)
        t_frame.append(time.perf_counter() - t0)
    t_geo = []
    for T in poses:
        t0 = time.perf_counter()
        renderer.render(T, colour=False)
        t_geo.append(time.perf_counter() - t0)
    for T in poses[: min(30, len(poses))]:
        renderer.render(T)  # sets the camera pose
        t0 = time.perf_counter()
        off.render(scene, flags=renderer._flags_color)
        t_color.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        off.render(scene, flags=renderer._flags_seg, seg_node_map=renderer._seg_map)
        t_seg.append(time.perf_counter() - t0)
    rss_after = rss_mb()
    renderer.close()

    ms = lambda x: 1e3 * float(x)  # noqa: E731
    med = np.median(t_frame)
    print(f"uw_sil render benchmark: {args.width}x{args.height}, {len(renderer.node_names)} mesh nodes, "
          f"shading={args.shading}, seafloor={args.seafloor}")
    print(f"  import uw_sil.sim.render/scene  : {ms(t_import):8.1f} ms")
    print(f"  load model                  : {ms(t_load):8.1f} ms")
    print(f"  import pyrender/PyOpenGL    : {ms(t_gl_import):8.1f} ms")
    print(f"  context creation (Renderer) : {ms(t_create):8.1f} ms  (GL context + scene conversion)")
    print(f"  first render                : {ms(t_first):8.1f} ms  (shader compile + upload)")
    print(f"  per frame, median / p90     : {ms(med):8.1f} / {ms(np.percentile(t_frame, 90)):.1f} ms "
          f"over {len(t_frame)} frames ({1.0 / med:.1f} fps)")
    one_pass = getattr(renderer, "_one_pass", False)
    if one_pass:        # the ids ride in the colour pass's alpha; the SEG pass only serves colour=False
        print(f"    colour pass (FLAT, ids in alpha, depth): {ms(np.median(t_color)):8.1f} ms  (one pass)")
        print(f"    (SEG pass alone, for colour=False  : {ms(np.median(t_seg)):8.1f} ms)")
    else:
        print(f"    colour pass (FLAT)        : {ms(np.median(t_color)):8.1f} ms")
        print(f"    SEG pass (ids + depth)    : {ms(np.median(t_seg)):8.1f} ms")
    passes = np.median(t_color) + (0.0 if one_pass else np.median(t_seg))
    print(f"    post-processing (numpy)   : {ms(med - passes):8.1f} ms")
    print(f"  RSS start / before / after  : {rss_start:.0f} / {rss_before:.0f} / {rss_after:.0f} MiB "
          f"(growth over the loop {rss_after - rss_before:+.1f} MiB)")
    print(f"  first frame: {int(first.hit.sum())} px hit, depth {np.nanmin(first.depth):.3f}"
          f"..{np.max(first.depth[first.hit]):.3f} m")
    print(f"  geometry only (colour=False): {ms(np.median(t_geo)):8.1f} ms median  (what sim_camera renders while "
          f"nobody takes its images)")
    print(f"render: frame_ms={ms(med):.1f} geometry_ms={ms(np.median(t_geo)):.1f} fps={1.0 / med:.1f}")


if __name__ == "__main__":
    main()
