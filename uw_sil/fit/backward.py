"""Backward optimization (paper Sec. 3.4, Algorithm 1): fit the simulator's 7 parameters to real frames.

At dive start the first K frames in which the panel is visible are taken from the recording. Each is
rendered ONCE at its recorded pose (clean image, range, depth, mask); a candidate parameter vector then
costs only the underwater model (:class:`uw_sil.sim.optics.PreparedRender`) and θ against the real frame
(:class:`uw_sil.metrics.theta.ThetaReference`), batched over a whole swarm / population. The objective is the
mean θ over the K frames, maximized by :func:`uw_sil.fit.optimize.optimize` (PSO as in the paper, or
CMA-ES).

Deviations from the paper's Algorithm 1 (each with its reason where it is implemented): θ is averaged
over K frames where the paper scores one real image ``I_g`` (frames at several ranges separate fog
from attenuation, :class:`FrameSelector`); θ2's histograms are split into panel and water pixels
(:class:`BackwardObjective`, ``hist_pixels``) and the candidates get the real frame's camera noise
(``sim_noise``); the search starts from a least-squares estimate (:func:`linear_start`) where the paper
starts from a random swarm; fits stop on convergence (:data:`FIT_TOL`) where the paper runs to
``t_max = 100``.

References
----------
.. [1] T. Doernbach, A. Gomez Chavez, C. A. Mueller and A. Birk, "High-Fidelity Deep-Sea Perception
   Using Simulation in the Loop", IFAC conference paper, 2018 (Sec. 3, Algorithm 1). ("the paper"
   throughout uw_sil.)
.. [2] J. Kennedy and R. Eberhart, "Particle swarm optimization", Proc. ICNN 1995 (the paper's optimizer).
.. [3] N. Hansen, "The CMA Evolution Strategy: A Tutorial", arXiv:1604.00772, 2016 (the faster alternative).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Optional

import numpy as np

from .._shared.fileio import write_text_atomic
from .._shared.process import default_threads
from ..sim.params import ParamSpace, UnderwaterParams

__all__ = ["FitFrame", "FrameSelection", "FrameSelector", "select_frames", "BackwardObjective", "FitResult", "fit_frames",
           "fit_bag", "write_params_yaml", "read_params_yaml", "write_json_atomic", "DEFAULT_NODE_NAME", "FIT_TOL",
           "FIT_PATIENCE", "CMAES_PATIENCE", "CMAES_MIN_STEP", "LINEAR_START_SIGMA0", "LINEAR_START_STDS",
           "spread_stride"]

DEFAULT_NODE_NAME = "/**"

#: Stop on convergence of a fit (:func:`fit_frames`): stop once the best θ gained no more than ``FIT_TOL``
#: over the last ``FIT_PATIENCE`` iterations. Chosen with bench/bench_convergence.py on four 320x240 trials
#: run to 100 iterations: CMA-ES (from the linear start, below) would have stopped at 36-64 (mean 55) giving
#: up at most 3e-4 of θ, PSO at 20-46 (mean 34; pyswarm's own rule stopped it at 25-100, mean 57) giving up
#: at most 6e-4; the parameters at the stop differ from those after 100 iterations by at most 0.08 (CMA-ES)
#: / 0.19 (PSO) of the recovery tolerances, and no recovery verdict changed.
FIT_TOL = 1e-4
FIT_PATIENCE = 20

#: CMA-ES from the linear start (:func:`fit_frames`' defaults for it): a window of 3 iterations instead of
#: :data:`FIT_PATIENCE`, and a stop once the search has collapsed (largest coordinate standard deviation below
#: :data:`CMAES_MIN_STEP` of the range: a tenth of the smallest recovery tolerance, 5 % of a_c = 0.05).
#: The dive-start fit waits for ship time: measured on the demo trial (640x480, K = 3), a window of 20
#: ran 46 iterations where the last 20 added 3.5e-5 of θ. A window of 5 (2026-11-25) then 3 (2026-11-30):
#: on the recovery bench's ten trials, 3 stopped after 4-12 iterations instead of 6-24, giving up 0-5.6e-4 of
#: θ on the fit frames (mean 2.3e-4; a tenth of what held-out frames resolve between two models, the
#: diagnosis' 0.003), with the same 10/10 recovered, the worst parameter of a trial at 0.28 of its
#: tolerance on average instead of 0.38 (bench/README.md).
CMAES_PATIENCE = 3
CMAES_MIN_STEP = 2.5e-4

#: CMA-ES from the linear start: initial step as a fraction of each range, and per-parameter factors
#: (a_r a_g a_b b_r b_g b_b rho_F). The linear start is close (measured: within 0.15 of the recovery
#: tolerances); a normalized step of 0.01 costs θ 2-9e-4 in attenuation, 2e-3 in fog, 2-5e-2 in the
#: background. With 0.1 for all (an earlier default) every sample was worse than the start for the first
#: 35-52 iterations (0.03: 17-38) on four 320x240 trials; with 0.01 the first improvement came at iteration
#: 1-10. At 640x480 (the demo trial, K = 3) 0.01 still gave 8 iterations without any improvement (the first
#: at iteration 8, when CMA-ES had shrunk its step to 0.0028); with 0.0025 the first came at iteration 2 and
#: 59 % of the final gain by iteration 4 (bench/bench_fit_speed.py, bench/README.md).
LINEAR_START_SIGMA0 = 0.0025
LINEAR_START_STDS = (1.0, 1.0, 1.0, 0.25, 0.25, 0.25, 1.0)


@dataclass
class FitFrame:
    """One real frame with its render at the recorded pose."""

    index: int              # position in the recording
    stamp_ns: int
    image: np.ndarray       # (H, W, 3) uint8 RGB, the real frame
    render: object          # uw_sil.sim.render.RenderResult
    coverage: float         # fraction of pixels on the panel
    image_index: int = -1   # position in the bag's image topic (Sample.index)
    pose_info: dict = None  # how the pose was found (Sample.pose_info: source, marker reprojection error...)

    @property
    def range_median(self) -> float:
        r = self.render.range[np.isfinite(self.render.range)]
        return float(np.median(r)) if r.size else float("inf")


@dataclass
class FrameSelection:
    frames: list
    skipped: list = field(default_factory=list)     # (index, reason)
    scanned: int = 0


class FrameSelector:
    """Online frame selection at dive start: offer frames one by one until ``k`` are taken.

    A frame is taken when the panel, rendered at the frame's recorded pose, covers at least
    ``min_coverage`` of the image; otherwise it is skipped with a reason (also when the panel is
    behind the camera). Frames that show nothing -- all one colour, e.g. lights off or a saturated
    sensor (every channel with a standard deviation below 1 grey level) -- are skipped too. Only
    every ``stride``-th frame is considered (spreads the K frames over more ranges, which separates
    fog from attenuation). Used offline by :func:`select_frames` and online by the ``backward_fit`` node.

    Parameters
    ----------
    renderer : :class:`uw_sil.sim.render.Renderer`
        Its camera is set from each sample's camera info.
    k : int
        Frames wanted.
    min_coverage : float
        Smallest fraction of the image the panel must cover.
    max_scan : int
        Frames of the recording looked at, at most.
    stride : int
    """

    def __init__(self, renderer, k: int = 3, min_coverage: float = 0.02, max_scan: int = 200, stride: int = 1):
        if k < 1:
            raise ValueError("k (frames to fit) must be >= 1")
        if not 0 <= min_coverage < 1:
            raise ValueError("min_coverage must be in [0, 1)")
        if stride < 1:
            raise ValueError("stride must be >= 1")
        if max_scan < 1:
            raise ValueError("max_scan must be >= 1")
        self.renderer, self.k, self.min_coverage, self.max_scan, self.stride = renderer, k, min_coverage, max_scan, stride
        self.frames: list = []
        self.skipped: list = []
        self.scanned = 0
        self._size = None
        self._unusable = 0      # frames skipped for their content, not for the panel's visibility

    @property
    def done(self) -> bool:
        return len(self.frames) >= self.k or self.scanned >= self.max_scan

    def offer(self, sample) -> bool:
        """Look at the next frame of the recording; True if it was taken."""
        if self.done:
            return False
        idx = self.scanned
        self.scanned += 1
        if idx % self.stride:
            return False
        h, w = sample.image.shape[:2]
        if self._size is None:
            self._size = (h, w)
        elif (h, w) != self._size:
            raise ValueError(f"frame {idx} is {w}x{h} but earlier frames are {self._size[1]}x{self._size[0]}: "
                             "fit frames of one camera stream only")
        flat = _uniform_reason(sample.image)
        if flat:
            self.skipped.append((idx, flat))
            self._unusable += 1
            return False
        if self.renderer.camera != sample.camera:
            self.renderer.camera = sample.camera
        rr = self.renderer.render(sample.pose)
        cov = float(np.mean(rr.labels == 1))
        if cov < self.min_coverage:
            z = float(sample.pose[2, 3])
            why = (f"the panel is behind the camera (its origin at z = {z:.2f} m in the optical frame)" if z <= 0
                   else f"panel covers {100 * cov:.1f}% of the image (< {100 * self.min_coverage:.1f}%)")
            self.skipped.append((idx, why))
            return False
        self.frames.append(FitFrame(idx, int(sample.stamp_ns), np.ascontiguousarray(sample.image), rr, cov,
                                    int(getattr(sample, "index", -1)), getattr(sample, "pose_info", None)))
        return True

    def result(self) -> FrameSelection:
        """The selection so far; ValueError "panel not visible ..." when no frame was taken."""
        if not self.frames:
            detail = (f"; {len(self.skipped)} skipped, e.g. frame {self.skipped[0][0]}: {self.skipped[0][1]}"
                      if self.skipped else "")
            what = "no usable frame among" if self._unusable else "panel not visible in any of"
            raise ValueError(f"{what} the first {self.scanned} frames{detail}")
        return FrameSelection(list(self.frames), list(self.skipped), self.scanned)


def _uniform_reason(image: np.ndarray) -> str:
    """Why a frame cannot be fitted because it shows nothing (all one colour), or "" if it can."""
    img = np.asarray(image)
    lo, hi = img.min(axis=(0, 1)), img.max(axis=(0, 1))
    if np.all(lo == hi):
        return f"the frame is uniform (every pixel {', '.join(str(int(v)) for v in lo)}): nothing to fit"
    if np.all(img.reshape(-1, img.shape[-1]).std(axis=0) < 1.0):
        mean = img.reshape(-1, img.shape[-1]).mean(axis=0)
        return (f"the frame is nearly uniform (mean {', '.join(f'{v:.1f}' for v in mean)}, standard deviation "
                f"below 1 grey level): nothing to fit")
    return ""


def select_frames(samples: Iterable, renderer, k: int = 3, min_coverage: float = 0.02, max_scan: int = 200,
                  stride: int = 1) -> FrameSelection:
    """Take the first ``k`` usable frames of a recording (see :class:`FrameSelector`).

    Raises
    ------
    ValueError
        When no frame in the first ``max_scan`` shows the panel ("panel not visible ..."), or frames
        differ in size.
    """
    sel = FrameSelector(renderer, k=k, min_coverage=min_coverage, max_scan=max_scan, stride=stride)
    for s in samples:
        sel.offer(s)
        if sel.done:
            break
    return sel.result()


HIST_PIXELS = ("split", "panel", "all")


def _hist_masks(frame: FitFrame, hist_pixels: str):
    panel = frame.render.labels == 1
    if hist_pixels == "all":
        return None
    if hist_pixels == "panel":
        return panel
    return [panel, ~panel]


class BackwardObjective:
    """Batched objective: mean θ over the fit frames for candidate vectors of a :class:`ParamSpace`.

    Calling it with X of shape (N, 7) (coordinates of ``space``) returns θ of shape (N,). NaN or inf
    results of degenerate candidates are returned as they are; the optimizer treats them as worst.

    Parameters
    ----------
    hist_pixels : {'split', 'panel', 'all'}
        Pixels of θ2's region histograms. ``'all'`` is the paper's criterion. ``'panel'`` counts
        only pixels where the rendered panel is (the median runs over the regions that contain
        some). ``'split'`` (default) is the mean of θ2 over panel pixels and θ2 over water pixels.
        With ``'all'`` the median over the 10x10 regions is decided by water regions whenever the
        panel covers fewer than half of them (always beyond ~1.5 m here), so θ2 then says nothing
        about attenuation or fog: measured on a synthetic trial, ±25 % of a_r moved θ by < 2e-4
        with ``'all'`` and by 0.08 with ``'panel'``. With ``'panel'`` alone the background colour
        is left to FSIMc, which hardly weighs flat water: fits then found wrong backgrounds.
    sim_noise : {'estimate', 'none'} or float
        Camera noise added to the candidates (a fixed realization per frame, so the objective stays
        deterministic): ``'estimate'`` (default) measures it per channel on the real frame's water
        pixels (:func:`uw_sil.sim.noise.estimate_noise_sigma`); a number gives sigma in grey levels.
        Without it FSIMc compares sensor noise with a noise-free render and prefers wrong
        parameters (see :mod:`uw_sil.sim.noise`).
    workers : int, optional
        Threads evaluating parts of a batch (default: :func:`uw_sil._shared.process.default_threads`).
        Results do not depend on it.
    batch : int
        Unused (kept for callers): candidates are simulated and scored one at a time, as planes
        (:meth:`uw_sil.sim.optics.PreparedRender.planar`, :meth:`uw_sil.metrics.theta.ThetaReference.score_planar`).
    """

    def __init__(self, frames: list, space: ParamSpace, channels: str = "HSV", fog: str = "exp2",
                 batch: int = 20, hist_pixels: str = "split", sim_noise="estimate", seed: int = 0,
                 workers: Optional[int] = None):
        from ..sim.noise import NoiseField
        from ..sim.optics import PreparedRender
        from ..metrics.theta import ThetaReference

        if not frames:
            raise ValueError("no frames to fit")
        self.space = space
        self.frames = frames
        self.prepared = [PreparedRender(f.render.rgb, f.render.range, f.render.depth, fog=fog) for f in frames]
        if hist_pixels not in HIST_PIXELS:
            raise ValueError(f"hist_pixels must be one of {HIST_PIXELS}, got {hist_pixels!r}")
        self.hist_pixels = hist_pixels
        # One set of θ references per worker thread (they reuse work buffers, so they are not shared).
        # FFTs, exp and most array work release the GIL: two threads on two cores give ~1.6-1.8x.
        self.workers = default_threads(workers)
        refs = [ThetaReference(f.image, channels=channels, hist_mask=_hist_masks(f, hist_pixels)) for f in frames]
        self._refs = [refs] + [[r.fork() for r in refs] for _ in range(self.workers - 1)]
        self.references = self._refs[0]
        self._pool = None
        self.noise_sigma = [self._noise_sigma(f, sim_noise) for f in frames]
        self.noise = [NoiseField(f.image.shape, s, seed=seed + i) if np.any(s > 0) else None
                      for i, (f, s) in enumerate(zip(frames, self.noise_sigma))]
        # The inner loop works on planes (3, H * W); the same realization, rearranged (NoiseField.apply is
        # elementwise).
        for nf in self.noise:
            if nf is not None:
                nf.field = np.ascontiguousarray(np.moveaxis(nf.field, -1, 0).reshape(nf.field.shape[-1], -1))
        self._bufs = [[(np.empty((3, f.image.shape[0] * f.image.shape[1]), dtype=np.float32), prep.work_buffers())
                       for f, prep in zip(frames, self.prepared)] for _ in range(self.workers)]
        self.n_calls = 0

    @staticmethod
    def _noise_sigma(frame: FitFrame, sim_noise) -> np.ndarray:
        from ..sim.noise import water_noise_sigma

        if isinstance(sim_noise, str):
            if sim_noise == "none":
                return np.zeros(3)
            if sim_noise != "estimate":
                raise ValueError(f"sim_noise must be 'estimate', 'none' or a number, got {sim_noise!r}")
            cover = getattr(frame.render, "cover", None)
            water = frame.render.labels == 0 if cover is None else cover == 0
            return water_noise_sigma(frame.image, water)
        sigma = np.broadcast_to(np.asarray(sim_noise, dtype=float), (3,)).copy()
        if not np.all(np.isfinite(sigma)) or np.any(sigma < 0):
            raise ValueError(f"sim_noise must be >= 0, got {sim_noise!r}")
        return sigma

    def __call__(self, X) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        P = np.clip(self.space.to_rgb(X), 0.0, None)
        P[:, 3:6] = np.clip(P[:, 3:6], 0.0, 1.0)
        ok = np.isfinite(P).all(axis=1)
        theta = np.full(len(X), np.nan)
        if not ok.any():
            return theta
        Pok = P[ok]
        acc = np.zeros(len(Pok))
        parts = [p for p in np.array_split(np.arange(len(Pok)), self.workers) if p.size]
        if len(parts) == 1:
            self._score_part(0, Pok, parts[0], acc)
        else:
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="uw_sil-theta")
            for fut in [self._pool.submit(self._score_part, w, Pok, idx, acc) for w, idx in enumerate(parts)]:
                fut.result()
        theta[ok] = acc / len(self.prepared)
        self.n_calls += len(X)
        return theta

    def _score_part(self, w: int, P: np.ndarray, idx: np.ndarray, acc: np.ndarray):
        """θ summed over frames for candidates ``P[idx]``, with worker ``w``'s references and buffers."""
        from ..sim.params import validate_rgb_params

        Pw = validate_rgb_params(P[idx]).astype(np.float32)
        for prep, ref, noise, (buf, work) in zip(self.prepared, self._refs[w], self.noise, self._bufs[w]):
            for j, p in zip(idx, Pw):
                prep.planar(p, out=buf, work=work)
                buf *= 255.0
                if noise is not None:
                    noise.apply(buf)
                acc[j] += ref.score_planar(buf)

    def close(self):
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


@dataclass
class FitResult:
    params: UnderwaterParams
    x_best: np.ndarray
    theta_best: float
    theta_start: float
    space: ParamSpace
    optim: object                      # uw_sil.fit.optimize.OptimResult
    frames: list
    skipped: list
    channels: str
    fog: str
    wall_time_s: float
    hist_pixels: str = "split"
    noise_sigma: list = None
    read_report: object = None         # uw_sil.bags.ReadReport of the bag (fit_bag), else None
    theta_x0: Optional[float] = None   # θ where the optimizer started (None: PSO's random swarm)
    images_without_pose: list = field(default_factory=list)   # (image index, reason) from the bag reader
    pose_source: str = ""

    @property
    def noise_level(self) -> float:
        """Mean estimated camera noise over frames and channels, in grey levels (0 without estimate)."""
        return float(np.mean(self.noise_sigma)) if self.noise_sigma else 0.0

    def summary(self) -> dict:
        o = self.optim
        return {
            "params": self.params.as_dict(),
            "x_best": [float(v) for v in self.x_best],
            "color_model": self.space.model,
            "names": list(self.space.names),
            "lower": [float(v) for v in self.space.lower],
            "upper": [float(v) for v in self.space.upper],
            "theta_before": float(self.theta_start),
            "theta_optimizer_start": None if self.theta_x0 is None else float(self.theta_x0),
            "theta_after": float(self.theta_best),
            "optimizer": o.method,
            "seed": o.seed,
            "settings": o.settings,
            "evaluations": int(o.n_evals),
            "iterations": int(o.n_iters),
            "converged_iteration": o.converged_iter,
            "stop_reason": o.stop_reason,
            "tol": float(o.tol),
            "patience": int(o.patience),
            "history_best_theta": [float(v) for v in o.history_best_f],
            "wall_time_s": float(self.wall_time_s),
            "channels": self.channels,
            "hist_pixels": self.hist_pixels,
            "noise_sigma_per_frame": [[float(v) for v in s] for s in (self.noise_sigma or [])],
            "fog": self.fog,
            "frames": [{"index": f.index, "stamp_ns": f.stamp_ns, "coverage": f.coverage,
                        "range_median_m": f.range_median, "image_index": f.image_index,
                        **({"pose": f.pose_info} if f.pose_info else {})} for f in self.frames],
            "skipped_frames": [{"index": i, "reason": r} for i, r in self.skipped],
            "pose_source": self.pose_source,
            "images_without_pose": [{"image_index": i, "reason": r} for i, r in self.images_without_pose],
        }


def fit_frames(frames: list, method: str = "pso", color_model: str = "rgb", channels: str = "HSV",
               fog: str = "exp2", hist_pixels: str = "split", sim_noise="estimate", lower=None, upper=None,
               seed: Optional[int] = 0,
               start: Optional[UnderwaterParams] = None, x0="linear", progress: bool = False,
               callback: Optional[Callable] = None, skipped=(), tol: float = FIT_TOL, patience: Optional[int] = None,
               **optim_options) -> FitResult:
    """Fit the 7 parameters to already selected frames.

    ``start`` (e.g. the simulator's current parameters) gives θ before the fit (``theta_start``); by default
    the centre of the bounds. ``x0`` is where the optimizer starts (θ there: ``theta_x0``):

    - ``'linear'`` (default): :func:`linear_start`, a least-squares estimate of Eq. 1 on the panel
      pixels, with CMA-ES' initial step reduced to :data:`LINEAR_START_SIGMA0` of each range, a quarter
      of that for the background (:data:`LINEAR_START_STDS`), unless ``sigma0`` is given;
    - ``'water'``: background from the mean real water colour, the rest at the centre of the bounds;
    - ``None``: the centre of the bounds (the paper's PSO: a random swarm);
    - a vector in the space's coordinates.

    The fit stops on convergence, when the best θ gained no more than ``tol`` over the last ``patience``
    iterations (:func:`uw_sil.fit.optimize.optimize`; ``stop_reason`` ``"converged"``), or after ``max_iter``
    iterations (default 100). ``patience=None`` (default) is :data:`CMAES_PATIENCE` for CMA-ES from the
    linear start, which then also stops when its step has collapsed (``min_step`` :data:`CMAES_MIN_STEP`,
    ``stop_reason`` ``"step"``), else :data:`FIT_PATIENCE`. ``patience=0`` turns that stop off;
    ``method="pso", x0=None, patience=0`` is the paper's PSO exactly (a random swarm of 20, up to 100
    iterations).

    For PSO a start is one particle of the otherwise random initial swarm. Measured on a 640x480
    synthetic trial (K = 3, 4.0/3.3/1.9 m), CMA-ES from the centre had θ 0.862 after 100 iterations
    (truth: 0.966; a_r 0.18 for 0.42); from the linear start it reached 0.966 in 40.
    """
    from .optimize import optimize

    t0 = time.perf_counter()
    # A population of 20 for CMA-ES too (cma's default for 7-D is 9): with 9, fits on synthetic trials
    # fell into a fog-for-attenuation local optimum (θ 0.921 vs 0.954 at the truth); with 20 they did not.
    optim_options.setdefault("swarm_size", 20)
    space = ParamSpace(color_model, lower, upper)
    obj = BackwardObjective(frames, space, channels=channels, fog=fog, hist_pixels=hist_pixels,
                            sim_noise=sim_noise, batch=int(optim_options.get("swarm_size") or 20))
    x_start = space.from_rgb(start.as_vector()) if start is not None else (space.lower + space.upper) / 2
    theta_start = float(obj(x_start[None])[0])
    if isinstance(x0, str):
        if x0 == "water":
            x0 = water_start(frames, space)
        elif x0 == "linear":
            x0 = linear_start(frames, space, fog=fog)
            if method == "cmaes":
                if "sigma0" not in optim_options:
                    optim_options["sigma0"] = LINEAR_START_SIGMA0
                    cma_options = dict(optim_options.get("cma_options") or {})
                    cma_options.setdefault("CMA_stds", list(LINEAR_START_STDS))
                    optim_options["cma_options"] = cma_options
                optim_options.setdefault("min_step", CMAES_MIN_STEP)
                if patience is None:
                    patience = CMAES_PATIENCE
        else:
            raise ValueError(f"x0 must be 'linear', 'water', None or a vector, got {x0!r}")
    if patience is None:
        patience = FIT_PATIENCE
    # θ where the search starts: x0, or the centre of the bounds (CMA-ES' first mean; PSO: a random swarm)
    x_opt_start = np.asarray(x0, dtype=float) if x0 is not None else \
        ((space.lower + space.upper) / 2 if method == "cmaes" else None)
    try:
        res = optimize(obj, space.lower, space.upper, method=method, seed=seed, progress=progress,
                       callback=callback, names=space.names, x0=x0, tol=tol, patience=patience, **optim_options)
        theta_x0 = None
        if x_opt_start is not None:
            # CMA-ES evaluates its start first (injected): the same point gives the same θ, bit for bit
            ev = res.evaluations
            if method == "cmaes" and len(ev) and ev.x[0].tobytes() == x_opt_start.tobytes() and np.isfinite(ev.f[0]):
                theta_x0 = float(ev.f[0])
            elif x_opt_start.tobytes() == x_start.tobytes():
                theta_x0 = theta_start
            else:
                theta_x0 = float(obj(x_opt_start[None])[0])
    finally:
        obj.close()
    params = UnderwaterParams.from_vector(np.clip(space.to_rgb(res.x_best), 0, None), model="rgb") \
        if space.model == "rgb" else UnderwaterParams.from_vector(res.x_best, model="hsv")
    return FitResult(params, np.asarray(res.x_best), float(res.f_best), theta_start, space, res, frames,
                     list(skipped), channels, fog, time.perf_counter() - t0, hist_pixels,
                     [s.tolist() for s in obj.noise_sigma], theta_x0=theta_x0)


def linear_start(frames: list, space: ParamSpace, fog: str = "exp2") -> np.ndarray:
    """A closed-form first estimate of all 7 parameters from the real frames and their renders.

    Not in the paper, whose PSO starts from a random swarm (Algorithm 1, line 1). From the centre of
    the bounds the paper's PSO stalled far from the truth on every synthetic trial tried (θ ≈ 0.75
    against 0.96 at the truth) and CMA-ES needed more than 100 iterations at 640x480; from this
    estimate CMA-ES reached the truth's θ in 40 (see :func:`fit_frames`, the README's deviations and
    ``bench/bench_convergence.py``).

    The background is the mean colour of the real water pixels (Eq. 1 at r = inf). On panel pixels,
    Eq. 1 with fog is ``I - b = T (i - b)`` with ``-ln T = a_c r + rho_F^2 z^2`` (exp2 fog), linear in
    ``(a_r, a_g, a_b, rho_F^2)``: solved by non-negative least squares over the pixels of all frames
    where the clean render differs from the background by more than 0.1 (weights ``|i - b|``, which
    tempers the noise of ``ln T`` where the contrast is small). Only a start for the optimizer: camera
    noise, blur and whatever the model lacks bias it. Falls back to the centre of the bounds for
    parameters it cannot estimate (no water, no usable panel pixels).
    """
    from scipy.optimize import nnls

    centre = (space.lower + space.upper) / 2
    b = _water_colour(frames)
    if b is None:
        return centre
    rgb = space.to_rgb(centre)
    rgb[3:6] = b
    rows, ys, ws = [], [], []
    for f in frames:
        m = (f.render.labels == 1) & np.isfinite(f.render.range)
        if not m.any():
            continue
        i = f.render.rgb[m].astype(float)
        I = f.image[m].astype(float) / 255.0
        r = f.render.range[m].astype(float)
        z = f.render.depth[m].astype(float)
        zf = z * z if fog == "exp2" else (z if fog == "exp" else np.zeros_like(z))
        for c in range(3):
            d = i[:, c] - b[c]
            T = (I[:, c] - b[c]) / np.where(np.abs(d) > 1e-6, d, 1.0)
            ok = (np.abs(d) > 0.1) & (T > 1e-3) & (T <= 1.5)
            if ok.sum() < 20:
                continue
            A = np.zeros((int(ok.sum()), 4))
            A[:, c] = r[ok]
            A[:, 3] = zf[ok]
            rows.append(A)
            ys.append(-np.log(np.minimum(T[ok], 1.0)))
            ws.append(np.abs(d[ok]))
    if rows:
        A, y, w = np.vstack(rows), np.concatenate(ys), np.concatenate(ws)
        if fog == "none":
            A = A[:, :3]
        sol, _ = nnls(A * w[:, None], y * w)
        seen = [np.any(A[:, c] != 0) for c in range(3)]
        for c in range(3):
            if seen[c]:
                rgb[c] = sol[c]
        if fog != "none" and np.any(A[:, 3] != 0):
            rgb[6] = np.sqrt(sol[3]) if fog == "exp2" else sol[3]
    return np.clip(space.from_rgb(rgb), space.lower, space.upper)


def _water_colour(frames: list):
    """Mean colour (0..1) of the real frames' water pixels (Eq. 1 at r = inf: the background); None if none."""
    water = [f.image[f.render.labels == 0] for f in frames]
    water = [w for w in water if w.size]
    if not water:
        return None
    return np.clip(np.concatenate(water).reshape(-1, 3).mean(axis=0) / 255.0, 0.0, 1.0)


def water_start(frames: list, space: ParamSpace) -> np.ndarray:
    """Start vector: background = mean real water colour, other parameters at the centre of the bounds."""
    centre = (space.lower + space.upper) / 2
    b = _water_colour(frames)
    if b is None:
        return centre
    rgb = space.to_rgb(centre)
    rgb[3:6] = b
    return np.clip(space.from_rgb(rgb), space.lower, space.upper)


def spread_stride(n_frames: int, k: int) -> int:
    """Stride that spreads ``k`` frames over ``n_frames`` (the first and, if it divides, the last one)."""
    return max(1, (n_frames - 1) // (k - 1)) if k > 1 else 1


def fit_bag(bag, k: int = 3, stride: Optional[int] = None, min_coverage: float = 0.02, max_scan: int = 200,
            model=None, source=None, **fit_options) -> FitResult:
    """Read a recording, select frames, render them and fit (see :func:`select_frames`, :func:`fit_frames`).

    ``source`` (:class:`uw_sil.bags.source.BagSource`) says which topics, calibration and pose source to
    read; default the standard topics (``/camera/image_raw``, ``/camera/camera_info``, ``/panel/pose``).
    Its ``model`` (the panel mesh) is used when ``model`` is not given.

    ``stride=None`` (default) spreads the ``k`` frames over the first ``max_scan`` frames of the recording
    (:func:`spread_stride`), so that they see the panel from different ranges, which separates fog from
    attenuation. With consecutive frames (``stride=1``) of the issue's trial (8 frames approaching from 4 m
    to 1.2 m; frames at 4.0, 3.9, 3.5 m) θ is higher away from the truth than at it, and CMA-ES fits
    missed the recovery tolerances for most seeds (bench/bench_repro.py; README).
    """
    from ..bags.source import BagSource
    from ..sim.render import Renderer

    source = BagSource(model=model) if source is None else source
    model = source.model if model is None else model
    if stride is None:
        n = 0
        counting = source.read(bag)
        try:
            for n, _ in enumerate(counting, start=1):
                if n >= max_scan:
                    break
        finally:
            counting.close()
        stride = spread_stride(n, k)
    with Renderer(model) as renderer:
        stream = source.read(bag)
        selector = FrameSelector(renderer, k=k, min_coverage=min_coverage, max_scan=max_scan, stride=stride)
        try:
            for s in stream:
                selector.offer(s)
                if selector.done:
                    break
        finally:
            stream.close()      # the report then holds what was read (and found damaged) so far
        if selector.scanned == 0:
            raise ValueError(f"{stream.report.path}: {_no_frames_reason(stream.report)}")
        sel = selector.result()
    result = fit_frames(sel.frames, skipped=sel.skipped, **fit_options)
    result.read_report = stream.report
    result.images_without_pose = [(i, why) for i, _, why in stream.report.skipped]
    result.pose_source = str(source.pose_from)
    return result


def _no_frames_reason(report) -> str:
    """Why a bag with image messages gave no sample (damaged storage, or no partners within tolerance)."""
    if report.errors:
        return "no frame could be read: " + "; ".join(report.errors)
    sync = report.sync
    if sync is not None and sync.received[0]:
        return (f"no frame could be read: none of the {sync.received[0]} images has a camera_info and a pose "
                f"within the stamp tolerance")
    return "no frame could be read: no complete image message in the bag"


def write_json_atomic(path, data) -> Path:
    """Write JSON through a temporary file and a rename: readers never see a half-written file."""
    return write_text_atomic(path, json.dumps(data, indent=2))


def write_params_yaml(path, params: UnderwaterParams, node_name: str = DEFAULT_NODE_NAME, fog: str = "exp2",
                      comment: str = "", noise_sigma: Optional[float] = None, effects: Optional[dict] = None) -> Path:
    """ROS 2 parameters file for the sim camera node (``--ros-args --params-file``), written atomically.

    ``noise_sigma`` (grey levels), when given, is the camera noise the fit estimated on the real frames.
    ``effects`` (``{name: {param: value}}``, see :mod:`uw_sil.sim.effects`) adds the read-only ``effects``
    list and one flat parameter ``<effect>.<param>`` per effect parameter."""
    import yaml

    from ..sim.model import effect_params_to_flat, normalize_effects

    ros_params = {**params.as_dict(), "fog_mode": fog}
    if noise_sigma is not None:
        ros_params["noise_sigma"] = float(noise_sigma)
    if effects:
        effects = normalize_effects(effects)
        ros_params["effects"] = ",".join(effects)
        ros_params.update(effect_params_to_flat(effects))
    body = {node_name: {"ros__parameters": ros_params}}
    # comment lines hold the bag's path: characters YAML does not allow (control characters) are escaped
    lines = ("".join(c if c.isprintable() else c.encode("unicode_escape").decode() for c in line)
             for line in comment.splitlines())
    text = "".join(f"# {line}\n" for line in lines) + yaml.safe_dump(body, sort_keys=False)
    return write_text_atomic(path, text)


def read_params_yaml(path, node_name: Optional[str] = None) -> dict:
    """Read a parameters file of :func:`write_params_yaml` (or any sim_camera parameters file).

    Takes the node entry ``node_name`` (default: the only one, or ``/**``). Effect parameters may be flat
    (``vignetting.k1: -0.3``) or nested (``vignetting: {k1: -0.3}``) as ROS 2 accepts both; effects are
    those in the ``effects`` list plus any with parameters in the file (parameters missing from the file
    take the listed preset or the defaults, as ``sim_camera`` does).

    Returns
    -------
    dict
        ``params`` (UnderwaterParams), ``fog`` (str), ``noise_sigma`` (float or None), ``effects``
        (``{name: {param: value}}``, composition order), ``node`` (the node entry read).

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ValueError
        With a message starting with ``path``: not YAML (with line and column), not a ROS 2
        parameters file, no entry for the node, a missing parameter, a value that is not a number or
        outside its physical range, an unknown fog mode or effect, a negative noise level.
    """
    import yaml

    from ..sim.effects import EFFECTS, get_effect
    from ..sim.model import normalize_effects
    from ..sim.optics import FOG_MODES

    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: cannot read: {exc}") from None
    try:
        doc = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or " ".join(str(exc).split())
        raise ValueError(f"{p}: not a valid YAML file: {problem}{where}") from None
    if not isinstance(doc, dict) or not any(isinstance(v, dict) and isinstance(v.get("ros__parameters"), dict)
                                            for v in doc.values()):
        raise ValueError(f"{p}: not a ROS 2 parameters file: expected <node>: {{ros__parameters: {{...}}}}")
    if node_name is None:
        node_name = next(iter(doc)) if len(doc) == 1 else DEFAULT_NODE_NAME
    if node_name not in doc or not isinstance(doc[node_name], dict) or "ros__parameters" not in doc[node_name]:
        raise ValueError(f"{p}: no 'ros__parameters' for node {node_name!r} (nodes: {', '.join(map(str, doc))})")
    flat = {}

    def walk(prefix, d):
        for k, v in d.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            if isinstance(v, dict):
                walk(key, v)
            else:
                flat[key] = v

    walk("", doc[node_name]["ros__parameters"])
    try:
        params = UnderwaterParams.from_dict(flat)
        fog = str(flat.get("fog_mode", "exp2"))
        if fog not in FOG_MODES:
            raise ValueError(f"fog_mode must be one of {', '.join(FOG_MODES)}, got {fog!r}")
        noise = flat.get("noise_sigma")
        if noise is not None and (isinstance(noise, bool) or not isinstance(noise, (int, float))
                                  or not np.isfinite(noise) or noise < 0):
            raise ValueError(f"noise_sigma must be a number >= 0 (grey levels), got {noise!r}")
        effects = {}                # as sim_camera reads its ``effects`` list: NAME (defaults) or NAME=mild|strong
        for item in (s.strip() for s in str(flat.get("effects", "")).split(",")):
            if item:
                name, _, level = (t.strip() for t in item.partition("="))
                effects[name] = get_effect(name).severity(level) if level else get_effect(name).defaults()
        for key, v in flat.items():                     # then the values in the file
            name, dot, param = key.partition(".")
            if dot and name in EFFECTS:
                effects.setdefault(name, EFFECTS[name].defaults())[param] = v
        effects = normalize_effects(effects)
    except ValueError as exc:
        raise ValueError(f"{p}: {exc}") from None
    return {"params": params, "fog": fog, "noise_sigma": None if noise is None else float(noise),
            "effects": effects, "node": node_name}
