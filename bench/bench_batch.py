"""Campaign scaling on this machine: 4 dives with 1 and 2 workers, local process pool and Dask LocalCluster.

Each dive is a synthetic 320x240 trial fitted with CMA-ES (K = 2 frames, 15 iterations, no report), the
same work `uw-sil batch` does per dive. Prints the wall time of each configuration and, last, the speed-up
of 2 workers over 1 on the local pool. Also the peak RSS per worker process (what to plan per dive).
The cores are shared, not oversubscribed: 1 worker fits with 2 θ threads, 2 workers with 1 each
(``threads_per_dive``) — a single dive is already parallel, so the speed-up measures what running
dives side by side adds on top of that. A run with 1 worker and 1 thread per dive shows how the
processes themselves scale.

    python bench/bench_batch.py [--dives 4] [--max-iter 15]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uw_sil.campaign import find_dives, run_campaign  # noqa: E402
from uw_sil.cli import main as uw_sil_main  # noqa: E402


def _peak_rss_mb() -> float:
    """Largest resident set of any finished child process (the pool's workers), in MB."""
    import resource

    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dives", type=int, default=4)
    ap.add_argument("--max-iter", type=int, default=15)
    a = ap.parse_args()
    env = {**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "osmesa")}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for i in range(a.dives):
            subprocess.run([sys.executable, "-m", "uw_sil.cli", "synth", "--out", str(tmp / "dives" / f"d{i}.mcap"),
                            "--frames", "4", "--width", "320", "--height", "240", "--seed", str(i)],
                           check=True, env=env, capture_output=True)
        dives = find_dives(str(tmp / "dives" / "*" / "*.mcap"))
        opts = {"frames": 2, "stride": 2, "optimizer": "cmaes", "max_iter": a.max_iter, "seed": 0, "report": False}
        times = {}
        t0 = time.perf_counter()
        run_campaign(dives, tmp / "local1t", ["fit"], opts, jobs=1, threads_per_dive=1, command=uw_sil_main)
        times[("local", "1t")] = time.perf_counter() - t0
        print(f"local pool, 1 worker, 1 thread per dive: {times[('local', '1t')]:.1f} s for {len(dives)} dives",
              flush=True)
        for jobs in (1, 2):
            t0 = time.perf_counter()
            rows = run_campaign(dives, tmp / f"local{jobs}", ["fit"], opts, jobs=jobs,
                                threads_per_dive=max(1, (os.cpu_count() or 1) // jobs), command=uw_sil_main)
            times[("local", jobs)] = time.perf_counter() - t0
            assert all(r["status"] == "ok" for r in rows), rows
            print(f"local pool, {jobs} worker(s): {times[('local', jobs)]:.1f} s for {len(dives)} dives", flush=True)
        try:
            import distributed
        except ImportError:
            print("dask: not installed (pip install 'uw-sil[dask]'), skipped")
        else:
            for jobs in (1, 2):
                with distributed.LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True,
                                              dashboard_address=None, silence_logs=40) as cl, \
                        distributed.Client(cl) as client:
                    t0 = time.perf_counter()
                    rows = run_campaign(dives, tmp / f"dask{jobs}", ["fit"], opts, executor=client.get_executor(),
                                        threads_per_dive=max(1, (os.cpu_count() or 1) // jobs), command=uw_sil_main)
                    times[("dask", jobs)] = time.perf_counter() - t0
                assert all(r["status"] == "ok" for r in rows), rows
                print(f"dask LocalCluster, {jobs} worker(s): {times[('dask', jobs)]:.1f} s", flush=True)
        print(f"peak RSS of a worker process: {_peak_rss_mb():.0f} MB")
        sp = times[("local", 1)] / times[("local", 2)]
        extra = ""
        if ("dask", 2) in times:
            extra = f" dask_speedup_2w={times[('dask', 1)] / times[('dask', 2)]:.2f}"
        print(f"2 workers against 1 at one thread per dive each: {times[('local', '1t')] / times[('local', 2)]:.2f}x")
        print(f"batch: speedup_2w={sp:.2f}{extra} dives={len(dives)} cores={os.cpu_count()}")


if __name__ == "__main__":
    main()
