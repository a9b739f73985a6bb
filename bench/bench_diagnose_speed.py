"""Diagnosis speed: a round's candidate refits in worker processes against the same diagnosis in one process,
measured in the same run on the same bags, with the documents compared number for number.

    .venv/bin/python bench/bench_diagnose_speed.py [--bag B ...] [--repeats 1] [--processes 2]

Without ``--bag`` it writes an 8-frame 640x480 trial with the vehicle's lamps and a seafloor concealed (the
project's own generator, seed 0) and diagnoses that. Each diagnosis runs ``uw_sil.fit.diagnose.diagnose_bag``
in this process, one process and ``--processes`` alternating; the machine's load (1-minute average) is
printed next to every run. Per bag: the time of each step (base fit, evidence, every round, elimination,
statistics) of both, and whether the two documents are the same apart from their times.

Last line: ``diagnose speed: one process <t> s, <n> processes <t> s (median over bags and repeats), ratio
<r>x, identical <k>/<m>``.
"""
import argparse
import os
import statistics
import sys
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


def _without_times(o):
    if isinstance(o, dict):
        return {k: _without_times(v) for k, v in o.items() if k not in ("timing", "time_s", "refit_s", "source")}
    if isinstance(o, list):
        return [_without_times(v) for v in o]
    return o


def _trial(d: str) -> str:
    from uw_sil.bags.synth import synthesize_trial, truth_path
    from uw_sil.sim.camera import CameraModel

    bag = os.path.join(d, "lamps_floor.mcap")
    synthesize_trial(bag, n_frames=8, seed=0, camera=CameraModel.from_fov(640, 480, 70.0),
                     effects={"artificial_light": "strong", "unmodeled_geometry": "mild"}, overwrite=True)
    tp = truth_path(bag)
    if tp.exists():
        tp.unlink()
    return bag


def main(argv=None) -> int:
    from uw_sil.fit.diagnose import diagnose_bag

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", action="append", default=[])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--processes", type=int, default=2)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="uw_sil-diagspeed-") as d:
        bags = args.bag or [_trial(d)]
        times = {1: [], args.processes: []}
        same = 0
        for bag in bags:
            for rep in range(args.repeats):
                docs = {}
                for p in ((1, args.processes) if rep % 2 == 0 else (args.processes, 1)):
                    load = os.getloadavg()[0]
                    t0 = time.perf_counter()
                    diag = diagnose_bag(bag, processes=p)
                    dt = time.perf_counter() - t0
                    times[p].append(dt)
                    docs[p] = _without_times(diag.to_json())
                    steps = " ".join(f"{k.removesuffix('_s')} {v:.1f}" for k, v in diag.timing.items()
                                     if k != "total_s")
                    print(f"{os.path.basename(bag)} processes {p}: {dt:.1f} s (load {load:.1f}); {steps}; verdict "
                          f"{[v['effect'] for v in diag.verdict]}", flush=True)
                ok = docs[1] == docs[args.processes]
                same += ok
                print(f"{os.path.basename(bag)}: documents {'identical' if ok else 'DIFFER'}", flush=True)
    t1, tn = statistics.median(times[1]), statistics.median(times[args.processes])
    n = len(times[1])
    print(f"diagnose speed: one process {t1:.1f} s, {args.processes} processes {tn:.1f} s (median of {n}), "
          f"ratio {t1 / tn:.2f}x, identical {same}/{n}")
    return 0 if same == n else 1


if __name__ == "__main__":
    sys.exit(main())
