"""Panel pose from the panel's ArUco markers, on frames through the full underwater model.

Part 1 -- pose accuracy: frames of the shipped panel rendered at random viewpoints (offsets of +-10 cm,
yaw +-15 deg, pitch +-10 deg, roll +-5 deg) at 1.2 / 2 / 3 / 4 m, degraded with the default synthetic
water (attenuation, veiling light, exp2 fog), Poisson-Gaussian sensor noise and optionally JPEG; the
pose from the markers (``uw_sil.sim.markers.MarkerPoseEstimator``) against the truth, from the marker
corners alone (``lm``) and after the ECC refinement on the rendered face (``ecc``, the default).

Part 2 -- does it matter for the fit: for each seed, a trial with a random ground truth (as
``bench_recovery.py``: 11 frames 3.5 -> 1.2 m, K = 3, CMA-ES from the linear start) is fitted once with
the true poses (``/panel/pose``) and once with poses from the markers, on the same frames. Success =
attenuation within 5 %, background within 0.01, fog within 10 % (the recovery criteria).

    .venv/bin/python bench/bench_marker_pose.py [--per-range 12] [--width 640] [--jpeg 90] [--seeds 3]

The last line is the median translation error at 2 m, in millimetres (ECC-refined poses). Timings are
only indicative on a shared machine.
"""
import argparse
import math
import os
import sys
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from uw_sil.bags.source import BagSource  # noqa: E402
from uw_sil.bags.synth import DEFAULT_TRUTH, SensorNoise, add_sensor_noise, load_truth, synthesize_trial  # noqa: E402
from uw_sil.fit.backward import fit_frames, select_frames  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.markers import MarkerPoseEstimator  # noqa: E402
from uw_sil.sim.render import Renderer  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402
from uw_sil.sim.simcam import SimCamera  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_recovery import errors, random_truth  # noqa: E402  -- the same truths and recovery criterion


def pose_error(T, T_true):
    dR = T_true[:3, :3].T @ T[:3, :3]
    return 1000 * float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), math.degrees(Rotation.from_matrix(dR).magnitude())


def jpeg(img, quality):
    import cv2

    ok, buf = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].copy()


def part_pose(args, cam):
    rng = np.random.default_rng(args.seed)
    print(f"pose from markers, {cam.width}x{cam.height}, {args.per_range} random views per range, water "
          f"{DEFAULT_TRUTH}, sensor noise{f', JPEG q{args.jpeg}' if args.jpeg else ''}")
    est = {"lm": MarkerPoseEstimator(refine="lm"), "ecc": MarkerPoseEstimator(refine="ecc")}
    median_2m = None
    with SimCamera(DEFAULT_TRUTH, camera=cam) as sim:
        for d in args.ranges:
            res = {k: [] for k in est}
            miss = {k: 0 for k in est}
            times = {k: [] for k in est}
            rms = []
            for _ in range(args.per_range):
                T = facing_pose(d, x=rng.uniform(-0.1, 0.1), y=rng.uniform(-0.08, 0.08),
                                yaw=math.radians(rng.uniform(-15, 15)), pitch=math.radians(rng.uniform(-10, 10)),
                                roll=math.radians(rng.uniform(-5, 5)))
                img = add_sensor_noise(sim.render(T).image, SensorNoise(), rng)
                if args.jpeg:
                    img = jpeg(img, args.jpeg)
                for k, e in est.items():
                    t0 = time.perf_counter()
                    mp = e.estimate(img, cam)
                    times[k].append(time.perf_counter() - t0)
                    if mp.T is None:
                        miss[k] += 1
                        continue
                    res[k].append(pose_error(mp.T, T))
                    if k == "ecc":
                        rms.append(mp.rms_px)
            for k in est:
                a = np.array(res[k]) if res[k] else np.full((1, 2), np.nan)
                print(f"  {d:.1f} m {k:3s}: posed {len(res[k])}/{args.per_range}; translation median "
                      f"{np.median(a[:, 0]):7.2f} mm, max {np.max(a[:, 0]):7.1f} mm; rotation median "
                      f"{np.median(a[:, 1]):6.3f} deg, max {np.max(a[:, 1]):6.2f} deg; "
                      f"{1000 * np.mean(times[k]):.0f} ms/frame"
                      + (f"; corner reprojection RMS median {np.median(rms):.2f} px" if k == "ecc" and rms else ""),
                      flush=True)
                if k == "ecc" and abs(d - 2.0) < 1e-9:
                    median_2m = (float(np.median(a[:, 0])), float(np.median(a[:, 1])))
    for e in est.values():
        e.close()
    return median_2m


def part_fit(args, cam):
    print(f"backward fit from true poses vs marker poses ({cam.width}x{cam.height}, K=3, CMA-ES "
          f"{args.max_iter} it{f', JPEG q{args.jpeg}' if args.jpeg else ''}):")
    ok = {"truth": 0, "markers": 0}
    for seed in range(args.seeds):
        rng = np.random.default_rng(1000 + seed)
        truth = random_truth(rng)
        with tempfile.TemporaryDirectory() as d:
            bag = os.path.join(d, "trial.mcap")
            fmt = "jpeg" if args.jpeg else "raw"
            topic = "/rov/cam/image_raw" + ("/compressed" if args.jpeg else "")
            synthesize_trial(bag, n_frames=11, seed=seed, params=truth, camera=cam, start_m=3.5, end_m=1.2,
                             image_topic=topic, image_format=fmt, jpeg_quality=args.jpeg or 95)
            assert np.allclose(load_truth(bag)["params"].as_vector(), truth.as_vector())
            line = []
            for name, pose_from in (("truth", "topic:/panel/pose"), ("markers", "markers")):
                src = BagSource(image_topic=topic, pose_from=pose_from)
                stream = src.read(bag)
                with Renderer(camera=cam) as r:
                    sel = select_frames(stream, r, k=3, stride=5)
                stream.close()
                t = time.perf_counter()
                fit = fit_frames(sel.frames, method="cmaes", seed=seed, max_iter=args.max_iter)
                rel_a, abs_b, rel_rho, good = errors(fit.params, truth)
                ok[name] += good
                line.append(f"{name}: {'OK  ' if good else 'MISS'} a {np.round(rel_a, 3)} b {np.round(abs_b, 4)} "
                            f"rho {rel_rho:.3f} θ {fit.theta_best:.4f} ({time.perf_counter() - t:.0f} s; images "
                            f"{[f.image_index for f in sel.frames]})")
            print(f"  seed {seed}: " + " | ".join(line), flush=True)
    print(f"recovered: from true poses {ok['truth']}/{args.seeds}, from marker poses {ok['markers']}/{args.seeds}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-range", type=int, default=12)
    ap.add_argument("--ranges", type=float, nargs="+", default=[1.2, 2.0, 3.0, 4.0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--jpeg", type=int, default=0, help="JPEG quality (0: no compression)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=3, help="fits of part 2 (0: skip it)")
    ap.add_argument("--max-iter", type=int, default=60)
    args = ap.parse_args()
    if 2.0 not in args.ranges:
        args.ranges.append(2.0)
    cam = CameraModel.from_fov(args.width, args.width * 3 // 4, 70.0)
    median_2m = part_pose(args, cam)
    if args.seeds:
        part_fit(args, cam)
    print(f"median pose error at 2 m (ECC-refined): {median_2m[0]:.3f} mm, {median_2m[1]:.3f} deg")
    print(f"{median_2m[0]:.3f}")


if __name__ == "__main__":
    sys.exit(main())
