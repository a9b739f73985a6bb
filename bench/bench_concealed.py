"""Proof on concealed data: does `uw-sil diagnose` name the physics hidden in a recording?

Trials: each effect of uw_sil.sim.effects at its mild and strong preset, effect-free controls, some
two-effect combinations, several seeds, written as bags by ``synthesize_trial`` ("own" generator); plus a
"foreign" variant of a few effects written independently in ``foreign_effects.py`` (other beam/PSF shapes,
noise structure, values, trajectories: yaw/pitch up to 15/10 deg, end range 1.2-1.8 m). Each bag is
diagnosed blind (only the bag; the truth stays in this script). Prints a confusion matrix (truth x top-1
verdict), top-1 accuracy over single-effect trials, false alarms on controls, held-out θ gains of correct
detections, time per trial; the foreign variant separately. Results are appended to ``results.jsonl`` in
``--out-dir`` (a rerun skips trials already there). Last line::

    concealed: top1=XX% false_alarm=YY% trials=N

    .venv/bin/python bench/bench_concealed.py [--seeds 2] [--width 640] [--frames 8] [--foreign-seeds 1]
        [--effects a,b,...] [--severities mild,strong] [--controls 3] [--no-pairs] [--out-dir DIR]

Run it in the background (``nohup ... &``): a trial takes 1-3 minutes on a 2-core machine.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

EFFECTS = ("artificial_light", "forward_scatter", "backscatter_coefficient", "vignetting", "sensor_noise",
           "marine_snow", "camera_response", "unmodeled_geometry", "pose_error")
PAIRS = (("artificial_light", "vignetting"), ("forward_scatter", "marine_snow"), ("camera_response", "pose_error"))
FOREIGN = ("artificial_light", "forward_scatter", "vignetting", "sensor_noise", "marine_snow", "camera_response",
           "backscatter_coefficient", "unmodeled_geometry", "pose_error")


def own_params(seed: int):
    """Deep-sea-like base parameters, varied per seed."""
    from uw_sil.sim.params import UnderwaterParams

    r = np.random.default_rng(500 + seed)
    return UnderwaterParams(a=tuple(r.uniform([0.3, 0.08, 0.05], [0.5, 0.15, 0.11])),
                            b=tuple(r.uniform([0.03, 0.25, 0.32], [0.09, 0.36, 0.46])), rho_f=float(r.uniform(0, 0.1)))


def make_trials(args) -> list:
    trials = []
    effects = args.effects.split(",") if args.effects else EFFECTS
    sev = args.severities.split(",")
    for seed in range(args.seeds):
        for i in range(args.controls):
            if i % args.seeds == seed % args.seeds or args.controls >= args.seeds:
                trials.append({"gen": "own", "effects": {}, "seed": seed * 10 + i})
        for e in effects:
            for s in sev:
                trials.append({"gen": "own", "effects": {e: s}, "seed": seed})
        if not args.no_pairs and seed == 0:
            for a, b in PAIRS:
                trials.append({"gen": "own", "effects": {a: "strong", b: "strong"}, "seed": seed})
    fe = args.foreign_effects.split(",") if args.foreign_effects else FOREIGN
    for seed in range(args.foreign_seeds):
        trials.append({"gen": "foreign", "effects": {}, "seed": 100 + seed})
        for e in fe:
            for s in sev:
                trials.append({"gen": "foreign", "effects": {e: s}, "seed": 100 + seed})
    dedup = {}
    for t in trials:
        dedup[key(t)] = t
    return list(dedup.values())


def key(t) -> str:
    eff = "+".join(f"{k}={v}" for k, v in sorted(t["effects"].items())) or "control"
    return f"{t['gen']}:{eff}:seed{t['seed']}"


def run_trial(t, args) -> dict:
    from uw_sil.bags.synth import synthesize_trial
    from uw_sil.fit.diagnose import diagnose_bag
    from uw_sil.sim.camera import CameraModel

    with tempfile.TemporaryDirectory(prefix="uw_sil-concealed-") as d:
        bag = os.path.join(d, "trial.mcap")
        t0 = time.perf_counter()
        if t["gen"] == "own":
            cam = CameraModel.from_fov(args.width, args.width * 3 // 4, 70.0)
            synthesize_trial(bag, n_frames=args.frames, seed=t["seed"], params=own_params(t["seed"]), camera=cam,
                             effects=dict(t["effects"]) or None, overwrite=True)
            # the truth sidecar is next to the bag: move it out of reach of the diagnosis
            from uw_sil.bags.synth import truth_path

            tp = truth_path(bag)
            if tp.exists():
                tp.unlink()
        else:
            from foreign_effects import synth_foreign

            synth_foreign(bag, dict(t["effects"]), n_frames=args.frames, seed=t["seed"], width=args.width)
        t_gen = time.perf_counter() - t0
        t0 = time.perf_counter()
        diag = diagnose_bag(bag, k=args.frames, max_candidates=args.max_candidates, seed=0)
        t_diag = time.perf_counter() - t0
    doc = diag.to_json()
    truth = sorted(t["effects"])
    pred = [v["effect"] for v in doc["verdict"]]
    top1 = pred[0] if pred else "none"
    return {"key": key(t), **t, "truth": truth, "pred": pred, "top1": top1,
            "base_heldout": doc["base"]["theta_heldout"], "final_heldout": doc["final"]["theta_heldout"],
            "gain": doc["final"]["theta_heldout"] - doc["base"]["theta_heldout"],
            "candidates": [(c["effect"], c["delta_heldout"], c.get("margin")) for c in doc["candidates"]],
            "screen": {e: s.get("screen_score") for e, s in doc["signatures"].items()},
            "time_s": t_diag, "gen_s": t_gen, "timing": doc["timing"]}


def summarize(rows, label: str):
    single = [r for r in rows if len(r["truth"]) == 1]
    ctrl = [r for r in rows if not r["truth"]]
    pairs = [r for r in rows if len(r["truth"]) == 2]
    names = sorted({r["truth"][0] for r in single} | {r["top1"] for r in rows} | {"none"})
    print(f"\n=== {label}: confusion matrix (rows: concealed effect, columns: top-1 verdict) ===")
    truths = ["none"] + sorted({r["truth"][0] for r in single})
    abbrev = {n: n[:8] for n in names}
    print(f"{'':26s}" + "".join(f"{abbrev[n]:>9s}" for n in names))
    for tr in truths:
        rr = ctrl if tr == "none" else [r for r in single if r["truth"][0] == tr]
        if not rr:
            continue
        counts = {n: sum(1 for r in rr if r["top1"] == n) for n in names}
        print(f"{tr:26s}" + "".join(f"{counts[n]:9d}" for n in names))
    for sev in ("mild", "strong"):
        ss = [r for r in single if list(r["effects"].values())[0] == sev]
        if ss:
            acc = np.mean([r["top1"] == r["truth"][0] for r in ss])
            print(f"{label} {sev}: top-1 {100 * acc:.0f}% ({len(ss)} trials)")
    top1 = float(np.mean([r["top1"] == r["truth"][0] for r in single])) if single else float("nan")
    fa = float(np.mean([bool(r["pred"]) for r in ctrl])) if ctrl else float("nan")
    correct = [r for r in single if r["top1"] == r["truth"][0]]
    gains = [r["gain"] for r in correct]
    if pairs:
        both = np.mean([set(r["truth"]) <= set(r["pred"]) for r in pairs])
        one = np.mean([r["top1"] in r["truth"] for r in pairs])
        print(f"{label} pairs: top-1 is one of the two {100 * one:.0f}%, both named {100 * both:.0f}% ({len(pairs)} trials)")
    if gains:
        print(f"{label} held-out θ gain on correct detections: mean {np.mean(gains):+.4f}, min {np.min(gains):+.4f}, "
              f"improved on {sum(g > 0 for g in gains)}/{len(gains)}")
    print(f"{label} time per trial: mean {np.mean([r['time_s'] for r in rows]):.0f} s, "
          f"max {np.max([r['time_s'] for r in rows]):.0f} s (diagnosis only; machine shared, indicative)")
    misses = [r for r in single if r["top1"] != r["truth"][0]]
    for r in misses:
        print(f"   miss: {r['key']}: verdict {r['pred']}, candidates {[(c[0], round(c[1], 4)) for c in r['candidates']]}")
    for r in ctrl:
        if r["pred"]:
            print(f"   false alarm: {r['key']}: verdict {r['pred']}")
    return top1, fa, len(rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--foreign-seeds", type=int, default=1)
    ap.add_argument("--controls", type=int, default=3)
    ap.add_argument("--effects", default=None, help="comma-separated subset of the own effects")
    ap.add_argument("--foreign-effects", default=None)
    ap.add_argument("--severities", default="mild,strong")
    ap.add_argument("--no-pairs", action="store_true")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--max-candidates", type=int, default=3)
    ap.add_argument("--out-dir", default="/tmp/uw_sil-concealed")
    ap.add_argument("--only-summary", action="store_true", help="print the summary of results.jsonl")
    args = ap.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res_path = out / "results.jsonl"
    done = {}
    if res_path.exists():
        for line in res_path.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done[r["key"]] = r
    trials = make_trials(args)
    if not args.only_summary:
        print(f"{len(trials)} trials ({sum(1 for t in trials if key(t) in done)} already done), {args.width} px wide, "
              f"{args.frames} frames", flush=True)
        for i, t in enumerate(trials):
            k = key(t)
            if k in done:
                continue
            try:
                r = run_trial(t, args)
            except Exception as e:      # a failed trial is reported, the bench goes on
                r = {"key": k, **t, "truth": sorted(t["effects"]), "pred": [], "top1": f"error:{type(e).__name__}",
                     "gain": 0.0, "candidates": [], "time_s": 0.0, "error": str(e)}
            done[k] = r
            with open(res_path, "a") as fh:
                fh.write(json.dumps(r) + "\n")
            print(f"[{i + 1}/{len(trials)}] {k}: top-1 {r['top1']} (verdict {r['pred']}), gain {r.get('gain', 0):+.4f}, "
                  f"{r['time_s']:.0f} s", flush=True)
    keys = {key(t) for t in trials}
    rows = [r for k, r in done.items() if k in keys]
    own = [r for r in rows if r["gen"] == "own"]
    foreign = [r for r in rows if r["gen"] == "foreign"]
    t1, fa, n = summarize(own, "own generator") if own else (float("nan"), float("nan"), 0)
    if foreign:
        ft1, ffa, fn = summarize(foreign, "foreign variant")
        print(f"foreign: top1={100 * ft1:.0f}% false_alarm={100 * ffa:.0f}% trials={fn}")
    print(f"concealed: top1={100 * t1:.0f}% false_alarm={100 * fa:.0f}% trials={n}")


if __name__ == "__main__":
    sys.exit(main())
