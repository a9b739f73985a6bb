"""The ``uw-sil`` command: the core library's offline tools on ROS 2 bags.

    uw-sil synth --out trial.mcap [--frames N] [--seed S] [--params a_r=0.4,...] [--storage mcap|sqlite3]
                 [--effects NAME[=mild|strong],...]
    uw-sil info trial.mcap
    uw-sil fit --bag trial.mcap [--frames K] [--optimizer pso|cmaes] [--color-model rgb|hsv] [--channels HSV]
               [--out fit.yaml] [--report DIR]
    uw-sil demo [--out-dir out]          # synth -> contact sheet -> fit -> report

Exit codes: 0 success, 1 bad input (message on stderr), 130 interrupted (no partial outputs left).
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .sim.params import RGB_NAMES, UnderwaterParams

__all__ = ["main", "build_parser"]


def _parse_params(text: str) -> UnderwaterParams:
    """``a_r=0.4,a_g=0.1,...`` (names from RGB_NAMES, missing ones from the default truth) or 7 numbers."""
    from .bags.synth import DEFAULT_TRUTH

    text = text.strip()
    if "=" not in text:
        vals = [float(v) for v in text.replace(",", " ").split()]
        if len(vals) != 7:
            raise ValueError(f"--params needs 7 numbers ({', '.join(RGB_NAMES)}) or name=value pairs")
        return UnderwaterParams.from_vector(vals)
    d = DEFAULT_TRUTH.as_dict()
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, _, value = item.partition("=")
        name = name.strip()
        if name not in d:
            raise ValueError(f"unknown parameter {name!r}; known: {', '.join(RGB_NAMES)}")
        d[name] = float(value)
    return UnderwaterParams.from_dict(d)


def _progress_bar(total: int, desc: str):
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, disable=None)

    def update(done, _total):
        bar.n = done
        bar.refresh()
        if done >= _total:
            bar.close()
    return update


def cmd_synth(args) -> int:
    from .sim.camera import CameraModel
    from .bags.synth import synthesize_trial, truth_path

    out = Path(args.out)
    params = _parse_params(args.params) if args.params else None
    camera = CameraModel.from_fov(args.width, args.height, args.hfov)
    kw = {} if params is None else {"params": params}
    # The bag writer removes a partial bag when rendering fails or is interrupted; the truth sidecar
    # is written only after the bag is complete.
    truth = synthesize_trial(out, n_frames=args.frames, seed=args.seed, camera=camera, storage=args.storage,
                             fog=args.fog, start_m=args.start, end_m=args.end, effects=args.effects,
                             progress=_progress_bar(args.frames, "render"), overwrite=args.force, **kw)
    print(f"wrote bag {truth['bag']} ({args.frames} frames) and {truth_path(out)}")
    if args.contact_sheet:
        _contact_sheet(out, Path(args.contact_sheet))
        print(f"wrote {args.contact_sheet}")
    return 0


def _contact_sheet(bag: Path, png: Path, rows: int = 4):
    from .bags import open_bag, read_samples
    from .sim.render import Renderer
    from .viz import contact_sheet, save_figure

    n = open_bag(bag).topics["/camera/image_raw"].count
    pick = set(np.unique(np.linspace(0, n - 1, min(rows, n)).round().astype(int)).tolist())
    items = []
    renderer = None
    try:
        for i, s in enumerate(read_samples(bag)):      # streamed: only the picked frames are kept
            if i not in pick:
                continue
            renderer = renderer or Renderer(camera=s.camera)
            items.append((f"frame #{i} ({np.linalg.norm(s.pose[:3, 3]):.2f} m)", s.image, renderer.render(s.pose)))
    finally:
        if renderer is not None:
            renderer.close()
    title = f"{bag.name}: recorded frames next to the clean render, depth and mask"
    save_figure(contact_sheet(items, title), png)


def cmd_info(args) -> int:
    from .bags import open_bag

    info = open_bag(args.bag)
    print(info.describe() if hasattr(info, "describe") else info)
    return 0


# SIGINTs seen by main(): some third-party code swallows KeyboardInterrupt (trimesh wraps exceptions of
# its optional imports), so long work also polls this list and outputs are written only if it is empty.
_INTERRUPTED: list = []


def _raise_if_interrupted(*_):
    if _INTERRUPTED:
        raise KeyboardInterrupt


def _sim_noise(text: str):
    if text in ("estimate", "none"):
        return text
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--sim-noise must be 'estimate', 'none' or a number of grey levels, got {text!r}") from None


def cmd_fit(args) -> int:
    from .fit.backward import fit_bag, write_json_atomic, write_params_yaml
    from .fit.report import write_report

    methods = [args.optimizer] + ([m for m in ("pso", "cmaes") if m != args.optimizer] if args.compare else [])
    fits = []
    for m in methods:
        print(f"fitting with {m} ({args.color_model}, channels {args.channels}) ...", file=sys.stderr)
        opts = {}
        if args.max_iter is not None:
            opts["max_iter"] = args.max_iter
        fits.append(fit_bag(args.bag, k=args.frames, stride=args.stride, min_coverage=args.min_coverage,
                            method=m, color_model=args.color_model, channels=args.channels, fog=args.fog,
                            hist_pixels=args.hist_pixels, sim_noise=_sim_noise(args.sim_noise),
                            x0=None if args.start == "centre" else args.start, callback=_raise_if_interrupted,
                            seed=args.seed, progress=True, **opts))
    _raise_if_interrupted()
    fit = fits[0]
    for i, reason in fit.skipped:
        print(f"skipped frame #{i}: {reason}", file=sys.stderr)
    comment = (f"uw_sil backward fit of {args.bag}: {fit.optim.method}, theta {fit.theta_start:.4f} -> "
               f"{fit.theta_best:.4f}, {fit.optim.n_evals} evaluations, {fit.wall_time_s:.1f} s")
    write_params_yaml(args.out, fit.params, node_name=args.node_name, fog=args.fog, comment=comment,
                      noise_sigma=fit.noise_level)
    summary = fit.summary()
    summary["bag"] = str(args.bag)
    if len(fits) > 1:
        summary["other_runs"] = [f.summary() for f in fits[1:]]
    summary_path = Path(args.summary) if args.summary else Path(args.out).with_suffix(".json")
    write_json_atomic(summary_path, summary)
    print(comment)
    print("fitted: " + ", ".join(f"{k}={v:.4f}" for k, v in fit.params.as_dict().items()))
    print(f"wrote {args.out} and {summary_path}")
    if args.report:
        truth = None
        try:
            from .bags.synth import load_truth

            truth = load_truth(args.bag)["params"].as_dict()
        except FileNotFoundError:
            pass
        page = write_report(fits, args.report, truth=truth, title=f"uw_sil backward fit: {Path(args.bag).name}")
        print(f"wrote report {page}")
    return 0


def cmd_demo(args) -> int:
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "trial.mcap"
    t0 = time.perf_counter()
    cmd_synth(build_parser().parse_args(["synth", "--out", str(bag), "--frames", str(args.frames), "--seed",
                                         str(args.seed), "--force", "--contact-sheet", str(out / "contact_sheet.png")]))
    fit_args = ["fit", "--bag", str(bag), "--frames", "3", "--stride", str(max(1, args.frames // 3)),
                "--optimizer", args.optimizer, "--out", str(out / "fit.yaml"), "--report", str(out / "report"),
                "--seed", str(args.seed)]
    if args.compare:
        fit_args.append("--compare")
    cmd_fit(build_parser().parse_args(fit_args))
    print(f"demo done in {time.perf_counter() - t0:.0f} s: open {out / 'report' / 'index.html'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="uw-sil", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="render a synthetic field trial into a ROS 2 bag (+ truth sidecar)")
    s.add_argument("--out", required=True, help="bag to write, e.g. trial.mcap")
    s.add_argument("--frames", type=int, default=30)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--params", help="ground truth: 'a_r=0.4,b_g=0.3,...' or 7 numbers " + " ".join(RGB_NAMES))
    s.add_argument("--storage", choices=["mcap", "sqlite3"], default=None,
                   help="default: from the suffix of --out (.mcap or .db3; none: mcap)")
    s.add_argument("--fog", choices=["exp2", "exp", "none"], default="exp2")
    s.add_argument("--width", type=int, default=640)
    s.add_argument("--height", type=int, default=480)
    s.add_argument("--hfov", type=float, default=70.0, help="horizontal field of view in water [deg]")
    s.add_argument("--start", type=float, default=4.0, help="range at the start of the approach [m]")
    s.add_argument("--end", type=float, default=1.2, help="range at the end of the approach [m]")
    s.add_argument("--effects", help="inject effects the base model lacks (recorded only in the truth sidecar): "
                   "'NAME[=mild|strong],...' (bare NAME: strong; NAME.PARAM=value overrides), NAME one of "
                   "artificial_light, forward_scatter, backscatter_coefficient, vignetting, sensor_noise, "
                   "marine_snow, camera_response, unmodeled_geometry, pose_error")
    s.add_argument("--contact-sheet", help="also write a PNG contact sheet here")
    s.add_argument("--force", action="store_true", help="overwrite an existing bag")
    s.set_defaults(func=cmd_synth)

    i = sub.add_parser("info", help="topics, counts and losses of a bag")
    i.add_argument("bag")
    i.set_defaults(func=cmd_info)

    f = sub.add_parser("fit", help="backward optimization: fit the 7 parameters to a recording")
    f.add_argument("--bag", required=True)
    f.add_argument("--frames", type=int, default=3, help="K: frames to fit (default 3)")
    f.add_argument("--stride", type=int, default=1, help="use every n-th frame (more ranges in the K frames)")
    f.add_argument("--min-coverage", type=float, default=0.02, help="skip frames where the panel covers less")
    f.add_argument("--optimizer", choices=["pso", "cmaes"], default="pso")
    f.add_argument("--compare", action="store_true", help="also run the other optimizer for the report")
    f.add_argument("--color-model", choices=["rgb", "hsv"], default="rgb")
    f.add_argument("--channels", default="HSV", help="HSV channels for the histogram criterion, e.g. HSV, V, HS")
    f.add_argument("--hist-pixels", choices=["split", "panel", "all"], default="split",
                   help="pixels of the histogram criterion: panel and water separately (default), the "
                        "rendered panel only, or all pixels (the paper)")
    f.add_argument("--sim-noise", default="estimate",
                   help="camera noise added to simulated candidates: estimate (from the real water), none, "
                        "or sigma in grey levels")
    f.add_argument("--fog", choices=["exp2", "exp", "none"], default="exp2")
    f.add_argument("--start", choices=["linear", "water", "centre"], default="linear",
                   help="optimizer start: least-squares estimate of Eq. 1 (default), background from the "
                        "water only, or the centre of the bounds (the paper)")
    f.add_argument("--max-iter", type=int, default=None)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--out", default="fit.yaml", help="ROS 2 parameters file for the sim camera node")
    f.add_argument("--summary", help="JSON summary (default: next to --out)")
    f.add_argument("--node-name", default="/**", help="node name key in the parameters file")
    f.add_argument("--report", help="write PNG figures and index.html here")
    f.set_defaults(func=cmd_fit)

    d = sub.add_parser("demo", help="synthesize a trial, fit it and write the report")
    d.add_argument("--out-dir", default="out")
    d.add_argument("--frames", type=int, default=30)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--optimizer", choices=["pso", "cmaes"], default="cmaes",
                   help="main fit (default CMA-ES; --compare also runs the other, the paper's PSO)")
    d.add_argument("--compare", action="store_true", default=True)
    d.add_argument("--no-compare", dest="compare", action="store_false")
    d.set_defaults(func=cmd_demo)

    from .nodes.launcher import add_commands as add_launch_commands  # `uw-sil launch`, `uw-sil play`
    add_launch_commands(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    interrupted = _INTERRUPTED
    interrupted.clear()

    def on_sigint(signum, frame):
        interrupted.append(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint) if threading.current_thread() is threading.main_thread() else None
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted: no output written", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError) as e:
        if interrupted:   # Ctrl-C inside a third-party import or callback may surface as another error
            print("interrupted: no output written", file=sys.stderr)
            return 130
        print(f"uw-sil {args.command}: error: {e}", file=sys.stderr)
        return 1
    except Exception:
        if interrupted:
            print("interrupted: no output written", file=sys.stderr)
            return 130
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


if __name__ == "__main__":
    sys.exit(main())
