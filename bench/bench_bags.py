"""Bag read speed: synchronized samples (image, camera_info, panel pose) per second from MCAP and SQLite3 bags.

Writes ``--frames`` 640x480 frames (a smooth image with noise, ``rgb8``; with ``--jpeg`` a third bag of the same
frames as ``sensor_msgs/CompressedImage`` JPEG q95) with a camera_info, a pose and a TF message per frame
(:func:`uw_sil.bags.write_trial`) into a temporary directory, then reads each bag whole with
:func:`uw_sil.bags.read_samples` (what ``uw-sil fit``, ``diagnose`` and ``enhance`` read with: messages
deserialized, images decoded, stamps paired) ``--repeats`` times, alternating between the bags; the median of the
repeats per bag. The bags are in the page cache after the first pass: this is the reader's speed, not the disk's.

    .venv/bin/python bench/bench_bags.py [--frames 300] [--repeats 3] [--jpeg]

Last line: ``bags: mcap=<n> sqlite3=<n> [jpeg_mcap=<n>] frames/s``.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from uw_sil.bags import read_samples, write_trial
from uw_sil.bags.records import Sample
from uw_sil.sim.camera import CameraModel
from uw_sil.sim.scene import facing_pose


def samples(n: int, width: int = 640, height: int = 480, seed: int = 0):
    """``n`` frames of an approach: a smooth image with Gaussian noise (as incompressible as a camera's)."""
    rng = np.random.default_rng(seed)
    cam = CameraModel.from_fov(width, height, 60.0)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    base = np.stack([40 + 30 * np.sin(xx / 50), 60 + 20 * np.cos(yy / 40), 80 + 0 * xx], -1)
    for k in range(n):
        img = np.clip(base + rng.normal(0, 3, base.shape), 0, 255).astype(np.uint8)
        yield Sample(1_700_000_000_000_000_000 + k * 100_000_000, img, cam,
                     facing_pose(4.0 - 2.8 * k / max(n - 1, 1)), cam.frame_id)


def read_rate(bag: Path) -> tuple:
    """(frames read, frames per second) of one whole pass over ``bag``."""
    t = time.perf_counter()
    n = sum(1 for _ in read_samples(bag))
    return n, n / (time.perf_counter() - t)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jpeg", action="store_true", help="also a bag of JPEG CompressedImage frames")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        bags = {"mcap": write_trial(Path(tmp) / "raw_mcap.mcap", samples(a.frames)),
                "sqlite3": write_trial(Path(tmp) / "raw_sqlite.db3", samples(a.frames))}
        if a.jpeg:
            bags["jpeg_mcap"] = write_trial(Path(tmp) / "jpeg.mcap", samples(a.frames), image_format="jpeg")
        for bag in bags.values():
            read_rate(bag)                                    # first pass: imports, page cache
        rates = {name: [] for name in bags}
        for _ in range(a.repeats):
            for name, bag in bags.items():
                n, fps = read_rate(bag)
                if n != a.frames:
                    raise SystemExit(f"{name}: read {n} of {a.frames} frames")
                rates[name].append(fps)
    print(f"{a.frames} frames 640x480 per bag, {a.repeats} passes each (alternating); frames per second:")
    for name, r in rates.items():
        print(f"  {name:10s} median {statistics.median(r):7.0f}  (passes: {', '.join(f'{v:.0f}' for v in r)})")
    print("bags: " + " ".join(f"{name}={statistics.median(r):.0f}" for name, r in rates.items()) + " frames/s")


if __name__ == "__main__":
    main()
