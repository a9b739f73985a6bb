"""Diagnosis speed: a round's candidate refits in worker processes against the same diagnosis in one process,
measured in the same run on the same bags, with the documents compared number for number.

    .venv/bin/python bench/bench_diagnose_speed.py [--bag B ...] [--repeats 1] [--processes 2]

Without ``--bag`` it writes an 8-frame 640x480 trial with the vehicle's lamps and a seafloor concealed (the
project's own generator, seed 0) and diagnoses that. Each diagnosis is a fresh ``uw-sil diagnose --bag B --json J
--processes P`` (P = 1: the code before the worker processes, θ on the process's threads), one process and
``--processes`` alternating which goes first; the machine's load (1-minute average) is printed next to every
run. Per bag: the time of each step (base fit, evidence, every round, elimination,
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


def _first_difference(a, b, path="") -> str:
    """Where two documents first differ (a key path and the two values)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in list(a) + [k for k in b if k not in a]:
            if k not in a or k not in b:
                return f"{path}.{k}: only in one"
            d = _first_difference(a[k], b[k], f"{path}.{k}")
            if d:
                return d
        return ""
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: {len(a)} against {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            d = _first_difference(x, y, f"{path}[{i}]")
            if d:
                return d
        return ""
    return "" if a == b else f"{path}: {a!r} against {b!r}"


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


def _diagnose(bag: str, processes: int, out: str) -> tuple:
    """(wall time, document) of a fresh ``uw-sil diagnose``."""
    import json
    import subprocess

    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "uw_sil.cli", "diagnose", "--bag", bag, "--json", out,
                    "--processes", str(processes)], check=True, stdout=subprocess.DEVNULL)
    dt = time.perf_counter() - t0
    with open(out) as f:
        return dt, json.load(f)


def main(argv=None) -> int:
    from uw_sil.fit.diagnose import without_times

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", action="append", default=[])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--processes", type=int, default=2)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="uw_sil-diagspeed-") as d:
        bags = args.bag or [_trial(d)]
        times = {1: [], args.processes: []}
        same = 0
        for b, bag in enumerate(bags):
            for rep in range(args.repeats):
                docs = {}
                for p in ((1, args.processes) if (rep + b) % 2 == 0 else (args.processes, 1)):
                    load = os.getloadavg()[0]
                    dt, doc = _diagnose(bag, p, os.path.join(d, f"diag_{b}_{rep}_{p}.json"))
                    times[p].append(dt)
                    docs[p] = without_times(doc)
                    steps = " ".join(f"{k.removesuffix('_s')} {v:.1f}" for k, v in doc["timing"].items()
                                     if k != "total_s")
                    print(f"{os.path.basename(bag)} processes {p}: {dt:.1f} s (load {load:.1f}); {steps}; verdict "
                          f"{[v['effect'] for v in doc['verdict']]}", flush=True)
                ok = docs[1] == docs[args.processes]
                same += ok
                sel = [[s["chosen"] for s in docs[p]["selection"]] for p in (1, args.processes)]
                print(f"{os.path.basename(bag)}: documents " + ("identical" if ok else
                      f"differ, first at {_first_difference(docs[1], docs[args.processes])}; selection "
                      f"{'the same' if sel[0] == sel[1] else 'DIFFERS'}"), flush=True)
    t1, tn = statistics.median(times[1]), statistics.median(times[args.processes])
    n = len(times[1])
    print(f"diagnose speed: one process {t1:.1f} s, {args.processes} processes {tn:.1f} s (median of {n}), "
          f"ratio {t1 / tn:.2f}x, identical {same}/{n}")
    return 0 if same == n else 1


if __name__ == "__main__":
    sys.exit(main())
