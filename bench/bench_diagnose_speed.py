"""Diagnosis speed, measured in the same run on the same bags, with the documents compared number for number:
a round's candidate refits in worker processes against the same diagnosis in one process, or (``--baseline
DIR``) this code against a checkout of earlier code, both with ``--processes``.

    .venv/bin/python bench/bench_diagnose_speed.py [--bag B ...] [--repeats 1] [--processes 2] [--baseline DIR]

Without ``--bag`` it writes an 8-frame 640x480 trial with the vehicle's lamps and a seafloor concealed (the
project's own generator, seed 0) and diagnoses that. Each diagnosis is a fresh ``uw-sil diagnose --bag B --json J
--processes P`` (P = 1: the code before the worker processes, θ on the process's threads), run from an empty
directory with ``PYTHONPATH`` on the code it measures; the two arms alternate which goes first, and the
machine's load (1-minute average) is printed next to every run. Per bag: the time of each step (base fit,
evidence, every round, elimination, statistics) of both, and whether the two documents are the same apart from
their times.

Last line: ``diagnose speed: <arm A> <t> s, <arm B> <t> s (median over bags and repeats), ratio <r>x,
identical <k>/<m>``.
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


HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def diagnose_fresh(bag: str, processes, out: str, code: str = HERE, seed=None) -> tuple:
    """(wall time, document) of a fresh ``uw-sil diagnose`` of the checkout ``code`` (``--processes``
    omitted when ``processes`` is None: the command's default; ``--seed`` when ``seed`` is not None). It runs
    beside ``out``: ``python -m`` puts the working directory first on the path, where another checkout would
    shadow ``code``."""
    import json
    import subprocess

    env = dict(os.environ, PYTHONPATH=os.path.abspath(code))
    more = [] if processes is None else ["--processes", str(processes)]
    more += [] if seed is None else ["--seed", str(seed)]
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "uw_sil.cli", "diagnose", "--bag", bag, "--json", out, *more],
                   check=True, stdout=subprocess.DEVNULL, env=env, cwd=os.path.dirname(out))
    dt = time.perf_counter() - t0
    with open(out) as f:
        return dt, json.load(f)


def main(argv=None) -> int:
    from uw_sil.fit.diagnose import without_times

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", action="append", default=[])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--baseline", help="checkout of earlier code: compared with this code, both at --processes")
    args = ap.parse_args(argv)
    if args.baseline:
        arms = {"baseline": (args.processes, args.baseline), "this code": (args.processes, HERE)}
    else:
        arms = {"one process": (1, HERE), f"{args.processes} processes": (args.processes, HERE)}
    (la, lb) = arms
    with tempfile.TemporaryDirectory(prefix="uw_sil-diagspeed-") as d:
        bags = args.bag or [_trial(d)]
        times = {a: [] for a in arms}
        same = 0
        for b, bag in enumerate(bags):
            for rep in range(args.repeats):
                docs = {}
                for i, arm in enumerate((la, lb) if (rep + b) % 2 == 0 else (lb, la)):
                    load = os.getloadavg()[0]
                    p, code = arms[arm]
                    dt, doc = diagnose_fresh(bag, p, os.path.join(d, f"diag_{b}_{rep}_{i}.json"), code)
                    times[arm].append(dt)
                    docs[arm] = without_times(doc)
                    steps = " ".join(f"{k.removesuffix('_s')} {v:.1f}" for k, v in doc["timing"].items()
                                     if k != "total_s")
                    print(f"{os.path.basename(bag)} {arm}: {dt:.1f} s (load {load:.1f}); {steps}; verdict "
                          f"{[v['effect'] for v in doc['verdict']]}", flush=True)
                ok = docs[la] == docs[lb]
                same += ok
                sel = [[s["chosen"] for s in docs[a]["selection"]] for a in (la, lb)]
                print(f"{os.path.basename(bag)}: documents " + ("identical" if ok else
                      f"differ, first at {_first_difference(docs[la], docs[lb])}; selection "
                      f"{'the same' if sel[0] == sel[1] else 'DIFFERS'}"), flush=True)
    ta, tb = statistics.median(times[la]), statistics.median(times[lb])
    n = len(times[la])
    print(f"diagnose speed: {la} {ta:.1f} s, {lb} {tb:.1f} s (median of {n}), ratio {ta / tb:.2f}x, "
          f"identical {same}/{n}")
    return 0 if same == n else 1


if __name__ == "__main__":
    sys.exit(main())
