"""Benchmark: theta per candidate (640x480 and 320x240 colour) against piq's FSIMc.

Run: ``.venv/bin/python bench/bench_theta.py``. Needs torch and piq for the comparison
(``pip install torch==2.13.0 piq``; benchmark only, never a runtime dependency).

What is measured (best of several repeats, wall clock, after a warm-up):

* ours: :class:`uw_sil.metrics.theta.ThetaReference` built once for a real 640x480 underwater frame,
  then ``evaluate`` on a batch of 20 float32 RGB candidates (blur, noise, colour cast);
  per-candidate time for theta = (FSIMc + theta_2) / 2, with 1 and 2 scipy.fft workers;
* piq: ``piq.fsim(ref, cand, data_range=255, chromatic=True)`` on float32 CPU tensors, torch
  limited to 1 thread, per evaluation (one pair per call, and the same 20 pairs as one batch;
  the faster of the two is used);
* accuracy: our float32 FSIMc (the cached-reference path) on the TID2013 pair against the
  published MATLAB value 0.92587, and against the float64 port on the benchmark candidates.

The last line is the speed ratio piq-FSIMc-time / our-theta-time, both single-threaded.
"""
from __future__ import annotations

import importlib.util
import os
import sys
import time
import types
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.ndimage import gaussian_filter

from uw_sil.metrics.fsim import fsim
from uw_sil.metrics.theta import ThetaReference

# The repository's test images (test/data/PROVENANCE.md); $UW_SIL_SHARED_DATA names another directory of that layout.
DATA = Path(os.environ.get("UW_SIL_SHARED_DATA") or Path(__file__).resolve().parents[1] / "test" / "data")
REAL = DATA / "real_underwater" / "suim_test" / "images" / "f_r_1965_.jpg"
N = 20
REPEATS = 5


def _import_piq_fsim():
    """``piq.fsim`` without importing all of piq.

    ``piq/__init__`` imports torchvision (for feature-extractor metrics), which may be missing or
    not match the installed torch; the FSIM module needs only torch, so it is imported through a
    bare package object.
    """
    try:
        from piq import fsim as piq_fsim  # noqa: PLC0415

        return piq_fsim
    except (ImportError, RuntimeError):
        spec = importlib.util.find_spec("piq")
        if spec is None:
            raise
        for mod in [m for m in sys.modules if m == "piq" or m.startswith("piq.")]:
            del sys.modules[mod]
        pkg = types.ModuleType("piq")
        pkg.__path__ = list(spec.submodule_search_locations)
        sys.modules["piq"] = pkg
        from piq.fsim import fsim as piq_fsim  # noqa: PLC0415

        return piq_fsim


def _candidates(ref: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = ref.astype(np.float32)
    out = np.empty((n,) + ref.shape, np.float32)
    for k in range(n):
        s = 0.3 + 2.5 * k / n
        cast = np.array([-3.0 * k, 0.5 * k, 2.0 * k], np.float32)
        out[k] = np.clip(gaussian_filter(x, (s, s, 0)) + cast + rng.normal(0, 3, x.shape), 0, 255)
    return out


def _best(fn, repeats=REPEATS) -> float:
    fn()  # warm-up (filter bank caches, FFT plans)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_ours(ref: np.ndarray, cands: np.ndarray, workers) -> dict:
    t0 = time.perf_counter()
    tref = ThetaReference(ref, workers=workers)
    ctor = time.perf_counter() - t0
    total = _best(lambda: tref.evaluate(cands))
    planes = [tref._hist.to_planar(c).reshape((3,) + c.shape[:2]).copy() for c in cands]
    t_fsim = _best(lambda: [tref._fsim.score_planar(p) for p in planes])
    t_hist = _best(lambda: [tref._hist.score_planar(p.reshape(3, -1)) for p in planes])
    return dict(ctor=ctor, per=total / len(cands), fsim=t_fsim / len(cands), hist=t_hist / len(cands), tref=tref)


def bench_piq(ref: np.ndarray, cands: np.ndarray):
    import torch  # noqa: PLC0415

    torch.set_num_threads(1)
    piq_fsim = _import_piq_fsim()
    x = torch.from_numpy(np.ascontiguousarray(cands.transpose(0, 3, 1, 2)))
    y = torch.from_numpy(np.ascontiguousarray(np.repeat(ref[None].astype(np.float32), len(cands), 0).transpose(0, 3, 1, 2)))

    def one_by_one():
        return [piq_fsim(x[k : k + 1], y[k : k + 1], data_range=255.0, chromatic=True, reduction="none") for k in range(len(cands))]

    def batched():
        return piq_fsim(x, y, data_range=255.0, chromatic=True, reduction="none")

    with torch.no_grad():
        single = _best(one_by_one, repeats=2) / len(cands)
        batch = _best(batched, repeats=2) / len(cands)
        values = batched().numpy().astype(np.float64)
    return single, batch, values, torch.__version__


def main() -> None:
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; batch of {N} float32 RGB candidates")
    ref640 = np.array(Image.open(REAL))
    assert ref640.shape == (480, 640, 3)
    ref320 = np.array(Image.fromarray(ref640).resize((320, 240), Image.BILINEAR))
    cands640 = _candidates(ref640, N)
    cands320 = _candidates(ref320, N)

    results = {}
    for label, ref, cands in (("640x480", ref640, cands640), ("320x240", ref320, cands320)):
        for workers in (1, 2):
            r = bench_ours(ref, cands, workers)
            results[(label, workers)] = r
            print(
                f"ours  {label} workers={workers}: theta {1e3 * r['per']:.2f} ms/candidate "
                f"(of which FSIMc {1e3 * r['fsim']:.2f}, theta2 {1e3 * r['hist']:.2f}); "
                f"reference set-up {1e3 * r['ctor']:.0f} ms once"
            )

    # accuracy of the fast (float32, cached-reference) path
    tid_ref = np.array(Image.open(DATA / "iqa_pairs" / "I01.BMP"))
    tid_dist = np.array(Image.open(DATA / "iqa_pairs" / "i01_01_5.bmp"))
    fast = ThetaReference(tid_ref).evaluate(tid_dist.astype(np.float32)).theta1[0]
    exact = fsim(tid_ref, tid_dist).fsimc
    print(f"accuracy: TID2013 I01 FSIMc fast path {fast:.7f}, float64 port {exact:.7f}, MATLAB 0.92587 "
          f"-> |fast - MATLAB| = {abs(fast - 0.92587):.1e}")
    ours_t1 = results[("640x480", 1)]["tref"].evaluate(cands640).theta1
    port = np.array([fsim(ref640, c).fsimc for c in cands640[:5]])
    print(f"accuracy: 640x480 candidates, max |fast - float64 port| = {np.abs(ours_t1[:5] - port).max():.1e}")

    try:
        single, batch, values, tv = bench_piq(ref640, cands640)
    except ImportError as exc:
        print(f"piq comparison skipped: {exc}")
        return
    piq_per = min(single, batch)
    print(f"piq   640x480 (torch {tv}, 1 thread, float32): FSIMc {1e3 * single:.1f} ms/eval one pair per call, "
          f"{1e3 * batch:.1f} ms/eval in a batch of {N}")
    print(f"piq vs ours FSIMc on the candidates: max |diff| = {np.abs(values - ours_t1).max():.1e} "
          "(piq is not an exact port of FeatureSIM.m)")
    ratio = piq_per / results[("640x480", 1)]["per"]
    print(f"speed ratio piq FSIMc / our theta per 640x480 evaluation, 1 thread each: {ratio:.1f}x")


if __name__ == "__main__":
    main()
