"""The ``uw-sil`` command: the core library's offline tools on ROS 2 bags.

    uw-sil synth --out trial.mcap [--frames N] [--seed S] [--params a_r=0.4,...|fit.yaml] [--storage mcap|sqlite3]
                 [--effects NAME[=mild|strong],...] [--image-topic T] [--compressed jpeg|png]
                 [--pose-in topic|tf|none] [--info-topic T|none] [--camera-yaml cam.yaml] [--distortion k1,...,k3]
    uw-sil info trial.mcap [BAG SOURCE] [--check N]
    uw-sil fit --bag trial.mcap [BAG SOURCE] [--frames K] [--optimizer pso|cmaes] [--color-model rgb|hsv]
               [--channels HSV] [--out fit.yaml] [--report DIR]
    uw-sil enhance --bag trial.mcap --params fit.yaml --out enhanced.mcap [--method sil|dcp|udcp] [--b-from-frame]
    uw-sil features --bag trial.mcap --params fit.yaml [--frames I,J] [--csv table.csv] [--report DIR]
    uw-sil diagnose --bag trial.mcap [--frames K] [--json out.json] [--report DIR] [--params-out fit.yaml]
    uw-sil diagnose --images DIR_OR_BAG [--image-topic T] [--json out.json]   # footage without a scene model
    uw-sil demo [--out-dir out]          # synth -> contact sheet -> fit -> enhance -> features -> report -> diagnose

BAG SOURCE (commands reading bags): [--image-topic T] [--info-topic T | --camera-info cam.yaml]
           [--pose-from topic:/panel/pose | tf:CAMERA_FRAME:PANEL_FRAME | markers] [--refine-pose none|ecc]
           [--model MESH]

Exit codes: 0 success; 2 bad input or command line: a wrong, damaged or unusable input file or option
value is reported as ONE line ``uw-sil: error: <file or option>: <what is wrong>`` on stderr (argparse's
own syntax errors add a usage line), and no output is left; 130 interrupted (no partial outputs left).
Anything else is a bug: Python's traceback and exit status 1.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .fit.backward import CMAES_PATIENCE, FIT_PATIENCE, FIT_TOL
from .sim.params import RGB_NAMES, UnderwaterParams

__all__ = ["main", "build_parser", "EXIT_BAD_INPUT"]

#: Exit status for a bad input file or option value (as argparse uses for command-line errors).
EXIT_BAD_INPUT = 2

# Errors of reading or validating an input: the user's to fix, reported as one line.
_INPUT_ERRORS = (ValueError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
                 PermissionError)


class InputError(Exception):
    """A bad input file or option value, already worded as ``<input>: <what is wrong>``."""


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


@contextmanager
def _input(name):
    """Errors of reading or checking the input ``name`` (a path or an option) become :class:`InputError`
    whose message starts with the input (unless the message already starts with it or its bag directory)."""
    try:
        yield
    except InputError:
        raise
    except _INPUT_ERRORS as exc:
        msg = _one_line(exc)
        names = {str(name)}
        if not str(name).startswith("-"):
            names.add(str(Path(name).with_suffix("")))     # trial.mcap -> the bag directory trial/
        if not any(msg.startswith(n) and msg[len(n):len(n) + 1] in (":", "/", " ") for n in names):
            msg = f"{name}: {msg}"
        raise InputError(msg) from exc


def _check_option(name: str, value, ok: bool, need: str):
    if not ok:
        raise InputError(f"{name}: must be {need}, got {value}")


def _parse_params(text: str) -> UnderwaterParams:
    """``a_r=0.4,a_g=0.1,...`` (names from RGB_NAMES, missing ones from the default truth) or 7 numbers."""
    from .bags.synth import DEFAULT_TRUTH

    def number(name, value):
        try:
            return float(value)
        except ValueError:
            raise ValueError(f"{name} must be a number, got {value.strip()!r}") from None

    text = text.strip()
    if "=" not in text:
        items = text.replace(",", " ").split()
        if len(items) != 7:
            raise ValueError(f"{len(items)} numbers given, 7 needed ({', '.join(RGB_NAMES)}), or name=value pairs")
        return UnderwaterParams.from_vector([number(n, v) for n, v in zip(RGB_NAMES, items)])
    d = DEFAULT_TRUTH.as_dict()
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, _, value = item.partition("=")
        name = name.strip()
        if name not in d:
            raise ValueError(f"unknown parameter {name!r}; known: {', '.join(RGB_NAMES)}")
        d[name] = number(name, value)
    return UnderwaterParams.from_dict(d)


def _synth_params(text: str):
    """(params, fog mode or None) of ``--params``: name=value pairs, 7 numbers, or a parameters file."""
    if Path(text).suffix in (".yaml", ".yml") or Path(text).is_file():
        from .fit.backward import read_params_yaml

        with _input(text):
            doc = read_params_yaml(text)
        return doc["params"], doc["fog"]
    with _input("--params"):
        return _parse_params(text), None


def _add_bag_source_args(parser, model: bool = True) -> None:
    """Options saying how to read a (field) bag: image topic, intrinsics, pose source (and panel model).

    Every command reading bags takes them (``info``, ``fit``, ...); :func:`_bag_source` turns the parsed
    arguments into a :class:`uw_sil.bags.source.BagSource`. Defaults (None here) are the standard topics.
    """
    g = parser.add_argument_group("which data of the bag (field trials)")
    g.add_argument("--image-topic", default=None,
                   help="sensor_msgs/Image or CompressedImage topic (default /camera/image_raw)")
    g.add_argument("--info-topic", default=None, help="sensor_msgs/CameraInfo topic (default /camera/camera_info)")
    g.add_argument("--camera-info", metavar="CAMERA_YAML", default=None,
                   help="camera intrinsics from a ROS camera_calibration YAML file instead of the info topic; "
                        "plumb_bob distortion is removed from the frames (rectified with OpenCV)")
    g.add_argument("--pose-from", default=None, metavar="SOURCE",
                   help="panel pose: topic:/panel/pose (default), tf:CAMERA_FRAME:PANEL_FRAME (from /tf and "
                        "/tf_static, interpolated to each image) or markers (the panel's ArUco markers)")
    g.add_argument("--tf-tolerance", type=float, default=None, metavar="S",
                   help="tf lookups may lie this far (s) outside the recorded transforms (default 0.1)")
    g.add_argument("--refine-pose", choices=["none", "ecc"], default=None,
                   help="ecc: refine topic/tf poses by aligning the rendered panel face with each frame "
                        "(the fit needs sub-pixel poses; converges from ~2-3 cm, ~1.5 deg); markers always are")
    if model:
        g.add_argument("--model", default=None, metavar="MESH",
                       help="panel mesh (default: the shipped intervention panel); for --pose-from markers "
                            "its markers are declared in MESH's .markers.yaml next to it")


_BAG_SOURCE_ARGS = ("image_topic", "info_topic", "camera_info", "pose_from", "tf_tolerance", "refine_pose")


def _bag_source(args):
    """The :class:`uw_sil.bags.source.BagSource` of options added by :func:`_add_bag_source_args`."""
    from .bags.source import DEFAULT_IMAGE_TOPIC, DEFAULT_INFO_TOPIC, DEFAULT_POSE_TOPIC, BagSource, PoseFrom

    from .bags.camera_yaml import load_camera_yaml

    calib = None
    if args.camera_info is not None:
        with _input(args.camera_info):
            calib = load_camera_yaml(args.camera_info)
    with _input("--pose-from"):
        pose_from = PoseFrom.parse(args.pose_from or f"topic:{DEFAULT_POSE_TOPIC}")
    kw = dict(image_topic=args.image_topic or DEFAULT_IMAGE_TOPIC, info_topic=args.info_topic or DEFAULT_INFO_TOPIC,
              camera_info=calib, pose_from=pose_from, model=getattr(args, "model", None))
    if args.tf_tolerance is not None:
        _check_option("--tf-tolerance", args.tf_tolerance, args.tf_tolerance >= 0, ">= 0 seconds")
        kw["tf_extrapolation_s"] = args.tf_tolerance
    if args.refine_pose is not None:
        kw["refine_pose"] = args.refine_pose
    with _input("--image-topic"):
        return BagSource(**kw)


def _pose_note(p) -> str:
    """How a frame's pose was found, for a progress line (empty for a plain recorded pose)."""
    p = p or {}
    if p.get("source") == "markers":
        return (f", pose from markers {p['ids']}: reprojection {p['reprojection_rms_px']:.2f} px RMS "
                f"(max {p['reprojection_max_px']:.2f}), refined by {p['refinement']}")
    if p.get("refinement") == "ecc":
        return (f", pose from {p['source']} refined by ECC: moved {p['correction_mm']:.1f} mm, "
                f"{p['correction_deg']:.2f} deg (correlation {p['ecc']:.3f})")
    if "refinement" in p:
        return f", pose from {p['source']}, {p['refinement']}"
    return ""


def _progress_bar(total: int, desc: str):
    """A ``progress(done, total)`` callback drawing :func:`uw_sil._shared.progress.progress_bar` on stderr."""
    from ._shared.progress import progress_bar

    bar = progress_bar(total, desc, unit="frame", file=sys.stderr)

    def update(done, _total):
        bar.update(done - bar.n)
        if done >= _total:
            bar.close()
    return update


def cmd_synth(args) -> int:
    from .sim.camera import CameraModel
    from .bags.synth import synthesize_trial, truth_path

    out = Path(args.out)
    params, fog = _synth_params(args.params) if args.params else (None, None)
    _check_option("--frames", args.frames, args.frames >= 1, ">= 1")
    with _input("--width/--height/--hfov"):
        camera = CameraModel.from_fov(args.width, args.height, args.hfov)
    kw = {} if params is None else {"params": params}
    fmt = args.compressed or "raw"
    image_topic = args.image_topic or ("/camera/image_raw" + ("/compressed" if fmt != "raw" else ""))
    info_topic = None if (args.info_topic or "").lower() == "none" else (args.info_topic or "/camera/camera_info")
    distortion = None
    if args.distortion:
        with _input("--distortion"):
            distortion = [float(v) for v in args.distortion.replace(",", " ").split()]
        _check_option("--distortion", args.distortion, len(distortion) == 5, "5 plumb_bob coefficients k1,k2,p1,p2,k3")
    if info_topic is None and not args.camera_yaml:
        raise InputError("--info-topic none: writes no camera_info, so --camera-yaml FILE is needed for the intrinsics")
    # The bag writer removes a partial bag when rendering fails or is interrupted; the truth sidecar
    # is written only after the bag is complete.
    with _input(args.out):
        truth = synthesize_trial(out, n_frames=args.frames, seed=args.seed, camera=camera, storage=args.storage,
                                 fog=args.fog or fog or "exp2", start_m=args.start, end_m=args.end,
                                 effects=args.effects, progress=_progress_bar(args.frames, "render"),
                                 overwrite=args.force, image_topic=image_topic, info_topic=info_topic,
                                 image_format=fmt, jpeg_quality=args.jpeg_quality, pose_in=args.pose_in,
                                 distortion=distortion, camera_yaml=args.camera_yaml, **kw)
    print(f"wrote bag {truth['bag']} ({args.frames} frames) and {truth_path(out)}"
          + (f" and {args.camera_yaml}" if args.camera_yaml else "") + f": images on {image_topic}, pose in "
          f"{args.pose_in}")
    if args.contact_sheet:
        from .bags.source import BagSource

        pose_from = {"topic": f"topic:{truth['pose_topic']}", "none": "markers",
                     "tf": f"tf:{truth['camera_frame']}:{truth['panel_frame']}"}[args.pose_in]
        source = BagSource(image_topic=image_topic, info_topic=info_topic, camera_info=args.camera_yaml,
                           pose_from=pose_from)
        _contact_sheet(out, Path(args.contact_sheet), source=source)
        print(f"wrote {args.contact_sheet}")
    return 0


def _contact_sheet(bag: Path, png: Path, rows: int = 4, source=None):
    from .bags import open_bag
    from .bags.source import BagSource
    from .sim.render import Renderer
    from .viz import contact_sheet, save_figure

    source = source or BagSource()
    n = open_bag(bag).topics[source.image_topic].count
    pick = set(np.unique(np.linspace(0, n - 1, min(rows, n)).round().astype(int)).tolist())
    items = []
    renderer = None
    try:
        for s in source.read(bag):      # streamed: only the picked frames are kept
            i = s.index
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
    from .bags.source import describe_sources

    with _input(args.bag):
        info = open_bag(args.bag)
        print(info.describe() if hasattr(info, "describe") else info)
        print(describe_sources(args.bag))
    if any(getattr(args, k) is not None for k in _BAG_SOURCE_ARGS) or args.check:
        _check_option("--check", args.check, args.check >= 0, ">= 0")
        source = _bag_source(args)
        n = max(1, args.check or 5)
        got = []
        with _input(args.bag):
            stream = source.read(args.bag)
            try:
                for s in stream:
                    got.append(s)
                    if len(got) >= n:
                        break
            finally:
                stream.close()
        rep = stream.report
        print(f"reading {source.describe()}: {len(got)} frame(s) with a pose in the first "
              f"{len(got) + len(rep.skipped)} image(s)")
        for s in got:
            print(f"  image #{s.index}: {s.camera.width}x{s.camera.height}, panel at "
                  f"{np.linalg.norm(s.pose[:3, 3]):.2f} m{_pose_note(s.pose_info)}")
        for i, _, why in rep.skipped:
            print(f"  image #{i}: no pose: {why}")
        for w in rep.warnings + rep.notes:
            print(f"  note: {w}")
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
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0 or value == float("inf"):
        raise InputError(f"--sim-noise: must be 'estimate', 'none' or a number of grey levels, got {text!r}")
    return value


def _warn_if_damaged(bag) -> None:
    """One warning line when the bag is cut off or damaged (the fit then uses every intact frame)."""
    from .bags import open_bag

    with _input(bag):
        rep = open_bag(bag).report
    if rep.truncated:
        lost = f"; lost {rep.lost}" if rep.lost else ""
        print(f"warning: {bag}: cut off or damaged: {rep.bytes_unreadable} of {rep.bytes_total} bytes unreadable"
              f"{lost}; fitting the intact frames", file=sys.stderr)


def cmd_fit(args) -> int:
    from .fit.backward import fit_bag, write_json_atomic, write_params_yaml
    from .fit.optimize import warm_up
    from .fit.report import write_report

    methods = [args.optimizer] + ([m for m in ("pso", "cmaes") if m != args.optimizer] if args.compare else [])
    _check_option("--frames", args.frames, args.frames >= 1, ">= 1")
    _check_option("--stride", args.stride, args.stride is None or args.stride >= 1, ">= 1")
    _check_option("--min-coverage", args.min_coverage, 0 <= args.min_coverage < 1, "in [0, 1)")
    _check_option("--max-iter", args.max_iter, args.max_iter is None or args.max_iter >= 1, ">= 1")
    warm_up(*methods)          # the optimizer's library imports while the bag is read and the frames rendered
    sim_noise = _sim_noise(args.sim_noise)
    source = _bag_source(args)
    _warn_if_damaged(args.bag)
    fits = []
    for m in methods:
        print(f"fitting with {m} ({args.color_model}, channels {args.channels}) ...", file=sys.stderr)
        opts = {name: getattr(args, name) for name in ("max_iter", "tol", "patience") if getattr(args, name) is not None}
        with _input(args.bag):
            fits.append(fit_bag(args.bag, k=args.frames, stride=args.stride, min_coverage=args.min_coverage,
                                source=source, method=m, color_model=args.color_model, channels=args.channels, fog=args.fog,
                                hist_pixels=args.hist_pixels, sim_noise=sim_noise,
                                x0=None if args.start == "centre" else args.start, callback=_raise_if_interrupted,
                                seed=args.seed, progress=True, **opts))
    _raise_if_interrupted()
    fit = fits[0]
    rr = fit.read_report      # damage found while reading (a bad chunk, a bad record) was logged as a warning
    for i, reason in fit.images_without_pose:
        print(f"image #{i} has no pose: {reason}", file=sys.stderr)
    for i, reason in fit.skipped:
        print(f"skipped frame #{i}: {reason}", file=sys.stderr)
    for f in fit.frames:
        print(f"fit frame #{f.index} (image #{f.image_index}, {f.range_median:.2f} m, panel "
              f"{100 * f.coverage:.0f}%){_pose_note(f.pose_info)}", file=sys.stderr)
    comment = (f"uw_sil backward fit of {args.bag}: {fit.optim.method}, theta {fit.theta_start:.4f} -> "
               f"{fit.theta_best:.4f}, {fit.optim.n_evals} evaluations, {fit.optim.n_iters} iterations "
               f"(stop: {fit.optim.stop_reason}), {fit.wall_time_s:.1f} s")
    summary = fit.summary()
    summary["bag"] = str(args.bag)
    if rr is not None and (rr.truncated or rr.errors):
        summary["bag_damage"] = {"truncated": rr.truncated, "lost": rr.lost, "errors": list(rr.errors)}
    if len(fits) > 1:
        summary["other_runs"] = [f.summary() for f in fits[1:]]
    summary_path = Path(args.summary) if args.summary else Path(args.out).with_suffix(".json")
    with _input(args.out):
        write_params_yaml(args.out, fit.params, node_name=args.node_name, fog=args.fog, comment=comment,
                          noise_sigma=fit.noise_level)
    with _input(summary_path):
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


def _lazy_progress(desc: str):
    """A progress callback ``(done, total)`` that opens its bar on the first call (total known then)."""
    state = {}

    def update(done, total):
        if "bar" not in state:
            state["bar"] = _progress_bar(total, desc)
        state["bar"](done, total)
    return update


def _sil_model(args):
    """(UnderwaterModel, fog) from --params (required for SIL), or (None, None)."""
    from .enhance.sil import load_model_yaml

    if args.params is None:
        if args.method == "sil":
            raise ValueError("--params fit.yaml is required for --method sil (the fitted model)")
        return None, None
    model = load_model_yaml(args.params)
    return model, model.fog


def cmd_enhance(args) -> int:
    from .enhance.bagtool import ENHANCED_TOPIC, enhance_bag

    params, fog = _sil_model(args)
    res = enhance_bag(args.bag, args.out, params, method=args.method, fog=fog, t0=args.t0,
                      b_from_frame=args.b_from_frame, overwrite=args.force, progress=_lazy_progress("enhance"),
                      interrupted=_raise_if_interrupted)
    _raise_if_interrupted()
    print(f"wrote bag {res.path}: {ENHANCED_TOPIC} ({args.method}) for {res.frames_out} of {res.frames_in} frames "
          f"next to {res.copied} recorded messages; mean restored fraction {res.restored_fraction_mean:.3f}")
    if res.frames_out < res.frames_in:
        print(f"{res.frames_in - res.frames_out} frames had no pose within tolerance and were not enhanced",
              file=sys.stderr)
    if res.skipped_topics:
        print(f"not copied (message types unknown to ROS 2 Kilted): {', '.join(res.skipped_topics)}", file=sys.stderr)
    return 0


def _frame_pair(text, bag) -> tuple:
    from .bags import open_bag
    from .enhance.bagtool import default_feature_frames

    if text is None:
        return default_feature_frames(open_bag(bag).topics["/camera/image_raw"].count or 0)
    try:
        i, j = (int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--frames must be two frame numbers I,J, got {text!r}") from None
    if i == j or min(i, j) < 0:
        raise ValueError(f"--frames needs two different frames >= 0, got {text!r}")
    return i, j


def cmd_features(args) -> int:
    from .enhance.bagtool import enhance_all, feature_rows, frames_with_geometry, quality_markdown, quality_rows
    from .enhance.features import table_csv, table_markdown

    args.method = "sil"
    params, fog = _sil_model(args)
    i, j = _frame_pair(args.frames, args.bag)
    shown = [i, j]
    if args.report:                                 # Fig. 4 also shows a far frame of the approach
        far = max(0, min(i, j) // 3)
        if far not in shown:
            shown.append(far)
    frames = frames_with_geometry(args.bag, shown)
    _raise_if_interrupted()
    images = enhance_all(frames, params, fog, t0=args.t0, b_from_frame=args.b_from_frame)
    rows = feature_rows(frames[:2], images[:2], args.descriptors)
    _raise_if_interrupted()
    md = table_markdown(rows)
    print(f"feature matches between frames #{i} and #{j} of {args.bag}:\n")
    print(md)
    verified = {(r["pair"], r["descriptor"]): r["verified_matches"] for r in rows}
    descs = list(dict.fromkeys(r["descriptor"] for r in rows))
    for other in ("raw", "DCP", "UDCP"):
        k = sum(verified[("SIL", d)] > verified[(other, d)] for d in descs)
        print(f"SIL has more verified matches than {other} for {k} of {len(descs)} descriptors")
    if args.csv:
        table_csv(rows, args.csv)
        print(f"wrote {args.csv}")
    if args.report:
        from .enhance.report import write_forward_report

        quality = qmd = None
        try:
            from .bags.synth import load_truth

            load_truth(args.bag)
            quality = quality_rows(frames, images)
            qmd = quality_markdown(quality)
            print(qmd)
        except FileNotFoundError:
            pass                                    # a real trial: no clean radiance to compare with
        page = write_forward_report(args.report, frames, images, rows, md, quality, qmd or "",
                                    descriptor=args.figure_descriptor,
                                    title=f"uw_sil forward half: {Path(args.bag).name}",
                                    notes=f"SIL with {args.params} (t0 = {args.t0}); DCP/UDCP: He et al. 2011 / "
                                          f"Drews et al. 2013 (patch 15, omega 0.95, t0 0.1, guided filter r 60).")
        print(f"wrote report {page}")
    return 0


def cmd_diagnose(args) -> int:
    """Which physics does the recording hold that the simulation lacks? (uw_sil.fit.diagnose)

    Exit 0 whatever the verdict (also "none"); EXIT_BAD_INPUT with one line naming the reason when it cannot
    diagnose (unreadable bag, scene model never visible, too few frames)."""
    from .fit.backward import write_json_atomic

    if bool(args.bag) == bool(args.images):
        raise ValueError("give exactly one of --bag (recording with poses and a scene model) or --images")
    t0 = time.perf_counter()

    def progress(msg):
        print(f"[{time.perf_counter() - t0:5.0f} s] {msg}", file=sys.stderr, flush=True)

    if args.images:
        from .fit.imagediag import diagnose_images

        doc = diagnose_images(args.images, image_topic=args.image_topic, k=args.frames or 12, progress=progress)
        _raise_if_interrupted()
        for line in doc["summary"]:
            print(line)
        if args.json:
            write_json_atomic(args.json, doc)
            print(f"wrote {args.json}")
        return 0
    from .fit.diagnose import diagnose_bag, write_diagnosis_yaml

    diag = diagnose_bag(args.bag, k=args.frames or 8, model=args.model, image_topic=args.image_topic,
                        seed=args.seed, max_effects=args.max_effects, fog=args.fog, progress=progress,
                        interrupt=_raise_if_interrupted, processes=getattr(args, "processes", None))
    _raise_if_interrupted()
    for line in diag.summary_lines():
        print(line)
    print(f"held-out θ {diag.base['theta_heldout']:.4f} -> {diag.final['theta_heldout']:.4f} "
          f"(as sim_camera renders the models, noise and particles drawn: "
          f"{diag.base['theta_heldout_simulated']:.4f} -> {diag.final['theta_heldout_simulated']:.4f}); "
          f"{diag.timing['total_s']:.0f} s")
    if args.json:
        write_json_atomic(args.json, diag.to_json())
        print(f"wrote {args.json}")
    if args.params_out:
        eff = ", ".join(diag.final.get("effects", [])) or "none"
        write_diagnosis_yaml(args.params_out, diag, node_name=args.node_name, fog=args.fog,
                             comment=f"uw_sil diagnose of {args.bag}: effects {eff}; held-out theta "
                                     f"{diag.base['theta_heldout']:.4f} -> {diag.final['theta_heldout']:.4f}")
        print(f"wrote {args.params_out}")
    if args.report:
        from .fit.diagnose_report import write_diagnosis_report

        page = write_diagnosis_report(diag, args.report, title=f"uw_sil diagnosis: {Path(args.bag).name}")
        print(f"wrote report {page}")
    return 0


def cmd_demo(args) -> int:
    from .fit.optimize import warm_up

    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "trial.mcap"
    t0 = time.perf_counter()
    warm_up(*(("pso", "cmaes") if args.compare else (args.optimizer,)))     # imports during the synthesis
    cmd_synth(build_parser().parse_args(["synth", "--out", str(bag), "--frames", str(args.frames), "--seed",
                                         str(args.seed), "--force", "--contact-sheet", str(out / "contact_sheet.png")]))
    fit_args = ["fit", "--bag", str(bag), "--frames", "3", "--stride", str(max(1, args.frames // 3)),
                "--optimizer", args.optimizer, "--out", str(out / "fit.yaml"), "--report", str(out / "report"),
                "--seed", str(args.seed)]
    if args.compare:
        fit_args.append("--compare")
    cmd_fit(build_parser().parse_args(fit_args))
    # forward half: enhance the trial with the fitted model, then Table 2 / Fig. 4-5 into the same report
    cmd_enhance(build_parser().parse_args(["enhance", "--bag", str(bag), "--params", str(out / "fit.yaml"), "--out",
                                           str(out / "enhanced.mcap"), "--force"]))
    cmd_features(build_parser().parse_args(["features", "--bag", str(bag), "--params", str(out / "fit.yaml"),
                                            "--csv", str(out / "features.csv"), "--report", str(out / "report")]))
    if args.diagnose:
        # a second trial with physics the base model lacks (vehicle lamps, concealed: only the truth sidecar
        # says so): the diagnosis must find it, model it and show held-out θ improving
        hidden = out / "concealed.mcap"
        # 8 frames for the diagnosis and 2 more it sets aside as report frames (no fit or choice sees them)
        cmd_synth(build_parser().parse_args(["synth", "--out", str(hidden), "--frames", "10", "--seed",
                                             str(args.seed), "--force", "--effects", args.concealed]))
        cmd_diagnose(build_parser().parse_args(["diagnose", "--bag", str(hidden), "--json", str(out / "diagnose.json"),
                                                "--params-out", str(out / "diagnose.yaml"),
                                                "--report", str(out / "diagnose"), "--seed", str(args.seed)]))
        # the demo concealed it, so the demo may now open the sidecar the diagnosis never saw
        from .bags.synth import load_truth

        hidden_truth = sorted(load_truth(hidden).get("effects") or [])
        doc = json.loads((out / "diagnose.json").read_text())
        named = [v["effect"] for v in doc["verdict"]]
        print(f"concealed in the second dive: {', '.join(hidden_truth) or 'nothing'}; diagnosis: "
              f"{', '.join(named) or 'none'} -> {found_words(hidden_truth, named)}; held-out θ "
              f"{doc['base']['theta_heldout']:.4f} -> {doc['final']['theta_heldout']:.4f}"
              + (f", on the report frames {doc['base']['theta_report']:.4f} -> {doc['final']['theta_report']:.4f}"
                 if doc["final"].get("theta_report") is not None else ""))
    print(f"demo done in {time.perf_counter() - t0:.0f} s: open {out / 'report' / 'index.html'}"
          + (f" and {out / 'diagnose' / 'index.html'}" if args.diagnose else ""))
    return 0


#: Effects the demo's second dive conceals: several at once, as in every deep-sea dive.
DEMO_CONCEALED = "artificial_light=mild,vignetting=mild,marine_snow=mild"


def found_words(concealed: list, named: list) -> str:
    """What a diagnosis found of the effects a trial concealed: 'found', or 'NOT found: <missed>', and the names
    it gave that were not concealed."""
    missed = [e for e in concealed if e not in named]
    extra = [e for e in named if e not in concealed]
    if not concealed:
        head = "nothing concealed"
    else:
        head = f"NOT found: {', '.join(missed)}" if missed else "found"
    return head + (f" (also named, not concealed: {', '.join(extra)})" if extra else "")


def cmd_batch(args) -> int:
    from tqdm import tqdm

    from .campaign import find_dives, make_executor, run_campaign, summary_line

    dives = find_dives(args.bags)
    steps = [s.strip() for s in args.steps.split(",") if s.strip()]
    options = {"frames": args.frames, "stride": args.stride, "optimizer": args.optimizer, "max_iter": args.max_iter,
               "seed": args.seed, "report": not args.no_report}
    executor, close = (None, None) if args.executor == "local" else make_executor(args.executor, args.jobs)
    print(f"campaign of {len(dives)} dives, steps {','.join(steps)}, executor {args.executor} -> {args.out}",
          file=sys.stderr)
    bar = tqdm(total=len(dives), unit="dive", file=sys.stderr, disable=None)

    def progress(done, total, row):
        bar.update(1)
        state = "already done" if row.get("skipped") else row.get("status")
        bar.set_postfix_str(f"{row['dive']}: {state}")
        if bar.disable or row.get("status") != "ok":       # a line per dive in logs and pipes
            tqdm.write(f"[{done}/{total}] {row['dive']}: {state}"
                       + (f" ({row.get('error')})" if row.get("status") != "ok" else ""), file=sys.stderr)

    try:
        rows = run_campaign(dives, args.out, steps, options, executor=executor, jobs=args.jobs, force=args.force,
                            retry_failed=args.retry_failed, progress=progress,
                            threads_per_dive=args.threads_per_dive, command=main)
    finally:
        bar.close()
        if close:
            close()
    print(summary_line(rows))
    print(f"wrote {Path(args.out) / 'campaign.parquet'} and {Path(args.out) / 'campaign.csv'}")
    failed = sum(r.get("status") != "ok" for r in rows)
    return min(failed, 100)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="uw-sil", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="render a synthetic field trial into a ROS 2 bag (+ truth sidecar)")
    s.add_argument("--out", required=True, help="bag to write, e.g. trial.mcap")
    s.add_argument("--frames", type=int, default=30)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--params", help="ground truth: 'a_r=0.4,b_g=0.3,...', 7 numbers " + " ".join(RGB_NAMES)
                   + ", or a parameters file (.yaml) as `uw-sil fit` writes it")
    s.add_argument("--storage", choices=["mcap", "sqlite3"], default=None,
                   help="default: from the suffix of --out (.mcap or .db3; none: mcap)")
    s.add_argument("--fog", choices=["exp2", "exp", "none"], default=None,
                   help="fog mode (default: the parameters file's fog_mode, else exp2)")
    s.add_argument("--width", type=int, default=640)
    s.add_argument("--height", type=int, default=480)
    s.add_argument("--hfov", type=float, default=70.0, help="horizontal field of view in water [deg]")
    s.add_argument("--start", type=float, default=4.0, help="range at the start of the approach [m]")
    s.add_argument("--end", type=float, default=1.2, help="range at the end of the approach [m]")
    s.add_argument("--effects", help="inject effects the base model lacks (recorded only in the truth sidecar): "
                   "'NAME[=mild|strong],...' (bare NAME: strong; NAME.PARAM=value overrides), NAME one of "
                   "artificial_light, forward_scatter, backscatter_coefficient, port_refraction, vignetting, "
                   "sensor_noise, marine_snow, camera_response, unmodeled_geometry, pose_error, compression")
    s.add_argument("--contact-sheet", help="also write a PNG contact sheet here")
    s.add_argument("--force", action="store_true", help="overwrite an existing bag")
    fs = s.add_argument_group("field-style bags")
    fs.add_argument("--image-topic", default=None,
                    help="image topic (default /camera/image_raw, with --compressed /camera/image_raw/compressed)")
    fs.add_argument("--compressed", choices=["jpeg", "png"], default=None,
                    help="write sensor_msgs/CompressedImage instead of raw rgb8 images")
    fs.add_argument("--jpeg-quality", type=int, default=95)
    fs.add_argument("--info-topic", default=None,
                    help="camera_info topic (default /camera/camera_info); 'none': no camera_info (needs --camera-yaml)")
    fs.add_argument("--camera-yaml", default=None, metavar="FILE",
                    help="also write the camera's calibration as a ROS camera_calibration YAML file")
    fs.add_argument("--distortion", default=None, metavar="K1,K2,P1,P2,K3",
                    help="plumb_bob lens distortion of the synthetic camera, e.g. --distortion=-0.1,0.02,0,0,0")
    fs.add_argument("--pose-in", choices=["topic", "tf", "none"], default="topic",
                    help="record the panel pose as /panel/pose (default), only as a navigation tf tree "
                         "(map->odom->base_link->camera_optical_frame, map->panel), or not at all (markers)")
    s.set_defaults(func=cmd_synth)

    i = sub.add_parser("info", help="topics, counts and losses of a bag; image topics and pose sources")
    i.add_argument("bag")
    _add_bag_source_args(i)
    i.add_argument("--check", type=int, default=0, metavar="N",
                   help="read the first N frames with the given source and say which have a pose")
    i.set_defaults(func=cmd_info)

    f = sub.add_parser("fit", help="backward optimization: fit the 7 parameters to a recording")
    f.add_argument("--bag", required=True)
    _add_bag_source_args(f)
    f.add_argument("--frames", type=int, default=3, help="K: frames to fit (default 3)")
    f.add_argument("--stride", type=int, default=None,
                   help="use every n-th frame (default: spread the K frames over the bag's first 200 frames)")
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
    f.add_argument("--max-iter", type=int, default=None, help="iterations at most (default 100)")
    f.add_argument("--tol", type=float, default=None,
                   help=f"stop on convergence: best theta gained <= TOL over --patience iterations (default {FIT_TOL:g})")
    f.add_argument("--patience", type=int, default=None,
                   help=f"window of the stop on convergence, in iterations (default {FIT_PATIENCE}; {CMAES_PATIENCE} for "
                        "cmaes from the linear start, which also stops when its step has collapsed); 0: no such stop "
                        "(--optimizer pso --start centre --patience 0 is the paper's PSO exactly)")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--out", default="fit.yaml", help="ROS 2 parameters file for the sim camera node")
    f.add_argument("--summary", help="JSON summary (default: next to --out)")
    f.add_argument("--node-name", default="/**", help="node name key in the parameters file")
    f.add_argument("--report", help="write PNG figures and index.html here")
    f.set_defaults(func=cmd_fit)

    e = sub.add_parser("enhance", help="dehaze a recorded trial with the fitted model (SIL), or DCP/UDCP, "
                                       "into a new bag with /camera/image_enhanced")
    e.add_argument("--bag", required=True)
    e.add_argument("--params", help="fitted parameters (uw-sil fit --out fit.yaml); required for --method sil")
    e.add_argument("--out", required=True, help="bag to write, e.g. enhanced.mcap (directory enhanced/)")
    e.add_argument("--method", choices=["sil", "dcp", "udcp"], default="sil")
    e.add_argument("--b-from-frame", action="store_true",
                   help="re-estimate the background b on every frame from its water pixels")
    e.add_argument("--t0", type=float, default=0.1, help="lowest transmission divided by (gain cap 1/t0)")
    e.add_argument("--force", action="store_true", help="overwrite an existing output bag")
    e.set_defaults(func=cmd_enhance)

    ft = sub.add_parser("features", help="feature matches between two frames: raw, DCP, UDCP and SIL (Table 2)")
    ft.add_argument("--bag", required=True)
    ft.add_argument("--params", required=True, help="fitted parameters (fit.yaml)")
    ft.add_argument("--frames", help="two frame numbers I,J (default: at 55%% and 70%% of the trial)")
    ft.add_argument("--descriptors", nargs="+", help="default: ORB BRIEF SIFT SURF KAZE AKAZE")
    ft.add_argument("--csv", help="write the table as CSV here")
    ft.add_argument("--report", help="write Fig. 4 / Fig. 5 analogues and forward.html into this directory")
    ft.add_argument("--figure-descriptor", default="SIFT", help="descriptor of the Fig. 5 picture")
    ft.add_argument("--b-from-frame", action="store_true")
    ft.add_argument("--t0", type=float, default=0.1)
    ft.set_defaults(func=cmd_features)

    g = sub.add_parser("diagnose", help="find the physics a recording holds that the simulation lacks",
                       description="Fits the base model, locates the mismatch, refits the model with every "
                                   "effect in turn and adds the one that raises held-out θ (or lowers the held-out "
                                   "residual) most beyond its noise margin, round after round; effects new in every "
                                   "frame (particles, noise) by held-out statistics. Exit 0 whatever the verdict.")
    g.add_argument("--bag", help="recording with /camera/image_raw, /camera/camera_info, /panel/pose")
    g.add_argument("--images", help="footage without poses or scene model: a folder of images or a bag")
    g.add_argument("--image-topic", default="/camera/image_raw")
    g.add_argument("--frames", type=int, default=None, help="frames used, spread over the recording "
                                                            "(default 8 with --bag, 12 with --images); with --bag "
                                                            "up to 2 more are read, when the recording has them, "
                                                            "and set aside as report frames that no fit or choice "
                                                            "sees (θ_report in the JSON)")
    g.add_argument("--model", help="scene model file (default: the shipped intervention panel)")
    g.add_argument("--json", help="write the diagnosis JSON here")
    g.add_argument("--report", help="write HTML + PNG report into this directory")
    g.add_argument("--params-out", help="ROS 2 parameters file for sim_camera with the extended model")
    g.add_argument("--node-name", default="/**")
    g.add_argument("--max-effects", type=int, default=4,
                   help="effects the greedy forward selection adds at most (default 4); the effects new in every "
                        "frame (particles, noise, compression), judged on their statistics, come on top")
    g.add_argument("--fog", choices=["exp2", "exp", "none"], default="exp2")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--processes", type=int, default=None,
                   help="worker processes refitting a round's candidates side by side (default: the thread budget, "
                        "UW_SIL_THREADS or up to 2; 1: all in this process); the same selection, numbers equal to ~1e-7")
    g.set_defaults(func=cmd_diagnose)

    d = sub.add_parser("demo", help="synthesize a trial, fit it, enhance it, write the report, and diagnose a second dive with concealed effects")
    d.add_argument("--out-dir", default="out")
    d.add_argument("--frames", type=int, default=30)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--optimizer", choices=["pso", "cmaes"], default="cmaes",
                   help="main fit (default CMA-ES; --compare also runs the other, the paper's PSO)")
    d.add_argument("--compare", action="store_true", default=True)
    d.add_argument("--no-compare", dest="compare", action="store_false")
    d.add_argument("--diagnose", action="store_true", default=True,
                   help="also synthesize a trial with concealed effects and diagnose it (default)")
    d.add_argument("--no-diagnose", dest="diagnose", action="store_false")
    d.add_argument("--concealed", default=DEMO_CONCEALED,
                   help="effects concealed in the diagnosis trial (uw-sil synth --effects syntax; default "
                        f"{DEMO_CONCEALED}: what a deep-sea camera meets at once, the vehicle's lamps, the "
                        "port's vignetting and marine snow)")
    d.set_defaults(func=cmd_demo)

    b = sub.add_parser("batch", help="a campaign: fit (and diagnose, enhance) every dive of a folder of bags",
                       description="Runs the per-dive commands over many bags, on this machine (a process pool) "
                                   "or on a Dask cluster; resumable; a results table campaign.parquet/.csv. "
                                   "Exit status: the number of dives that failed (0: all ok).")
    b.add_argument("--bags", nargs="+", required=True,
                   help="glob pattern(s), quoted, e.g. 'dives/**/*.mcap' (** is recursive), or bag paths")
    b.add_argument("--out", required=True, help="results folder: <dive>/ per dive and campaign.parquet/.csv")
    b.add_argument("--steps", default="fit", help="comma-separated, in order: fit, diagnose, enhance (default fit)")
    b.add_argument("--executor", default="local",
                   help="'local' (process pool, spawn) or dask://HOST:PORT (a Dask scheduler; uw-sil[dask])")
    b.add_argument("--jobs", type=int, default=None, help="local workers (default: number of cores)")
    b.add_argument("--threads-per-dive", type=int, default=None,
                   help="threads one dive's fit may use (default: cores / jobs on the local pool; "
                        "the worker's default, up to 2, on a cluster)")
    b.add_argument("--force", action="store_true", help="redo every dive, also those already done")
    b.add_argument("--retry-failed", action="store_true", help="redo the dives that failed last time")
    b.add_argument("--frames", type=int, default=None, help="K frames per fit (default: uw-sil fit's)")
    b.add_argument("--stride", type=int, default=None)
    b.add_argument("--optimizer", choices=["pso", "cmaes"], default="cmaes")
    b.add_argument("--max-iter", type=int, default=None)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--no-report", action="store_true", help="skip the per-dive HTML/PNG reports")
    b.set_defaults(func=cmd_batch)

    from .nodes.launcher import add_commands as add_launch_commands  # `uw-sil launch`, `uw-sil play`
    add_launch_commands(sub)
    return p


@contextmanager
def _warnings_to_stderr():
    """The library's logged warnings (damaged bags, dropped frames...) as ``warning: ...`` lines on stderr."""
    import logging

    handler = logging.StreamHandler(sys.stderr)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter("warning: %(message)s"))
    logger = logging.getLogger("uw_sil")
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    interrupted = _INTERRUPTED
    interrupted.clear()

    def on_sigint(signum, frame):
        interrupted.append(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint) if threading.current_thread() is threading.main_thread() else None
    try:
        with _warnings_to_stderr():
            return args.func(args)
    except KeyboardInterrupt:
        print("interrupted: no output written", file=sys.stderr)
        return 130
    except (InputError, *_INPUT_ERRORS) as e:
        if interrupted:   # Ctrl-C inside a third-party import or callback may surface as another error
            print("interrupted: no output written", file=sys.stderr)
            return 130
        print(f"uw-sil: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
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
