"""The backward-optimization criterion theta = (theta_1 + theta_2) / 2 (paper Sec. 3.4, Eq. 4).

theta_1 is FSIMc (paper Eq. 2; :mod:`uw_sil.metrics.fsim`, a port of ``FeatureSIM.m``) and theta_2 the
HSV region-histogram similarity (Eq. 3 as ``1 - median distance``, :mod:`uw_sil.metrics.histsim`; why the
paper's distance is not used: :func:`uw_sil.metrics.histsim.hsv_histogram_similarity`). Both are
similarities in [0, 1], so the optimizer maximizes theta, as Algorithm 1 does.

One real reference frame is compared with many simulated candidates: :class:`ThetaReference`
does all reference-only work (phase congruency, gradient magnitude and chroma of the
reference, its region histograms) once in the constructor and then scores candidate stacks;
:func:`mean_theta` averages theta over several reference frames (a dive's first K frames).

References
----------
.. [1] T. Doernbach, A. Gomez Chavez, C. A. Mueller and A. Birk, "High-Fidelity Deep-Sea Perception
   Using Simulation in the Loop", IFAC conference paper, 2018 (Eq. 2-4, Algorithm 1). ("the paper"
   throughout uw_sil.)
.. [2] L. Zhang, L. Zhang, X. Mou and D. Zhang, "FSIM: A Feature Similarity Index for Image Quality
   Assessment", IEEE Trans. Image Processing 20(8), 2378-2386, 2011 (theta_1 = FSIMc).
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from .._shared.checks import check_image, check_values
from .fsim import FSIMReference
from .histsim import HistogramReference, SplitHistogramReference

__all__ = ["ThetaReference", "ThetaScores", "mean_theta"]


class ThetaScores(NamedTuple):
    """theta and its components for N candidates (each an ndarray of shape (N,))."""

    theta: np.ndarray
    theta1: np.ndarray  # FSIMc
    theta2: np.ndarray  # HSV region-histogram similarity


class ThetaReference:
    """theta of candidate images against one real reference frame.

    Parameters
    ----------
    reference : ndarray, shape (H, W, 3)
        The real camera frame, RGB (not OpenCV's BGR), uint8 or float in 0..255.
    channels : str
        HSV channels of theta_2 (``"HSV"``, ``"HS"`` colour, ``"V"`` luminance, ...).
    regions : int
        theta_2 uses ``regions x regions`` rectangles (paper: 10).
    bins : None, int or dict
        theta_2 histogram bins (default H 36, S 32, V 32).
    mask : ndarray of bool, shape (H, W), optional
        Pixels that count in both terms (e.g. to exclude an overlay or the vehicle's own
        parts): FSIMc pools over them (at its downsampled grid), theta_2 histograms count only
        them. ``None``: all pixels, and theta_1 equals :func:`uw_sil.metrics.fsim.fsim` exactly.
    hist_mask : ndarray of bool (H, W), or a sequence of them, optional
        Pixels that count in theta_2 only (overrides ``mask`` there). With several masks,
        theta_2 is the mean of the per-mask theta_2 values. The backward optimizer passes the
        rendered object mask and the water mask, where the paper's histograms take all pixels
        (that deviation and its reason: :class:`uw_sil.fit.backward.BackwardObjective`,
        ``hist_pixels``).
    dtype : {numpy.float32, numpy.float64}
        Working precision of the candidate FFTs (float32: agrees with float64 to ~1e-7 in
        theta_1, about twice as fast).
    workers : int, optional
        Threads for ``scipy.fft``.

    Notes
    -----
    Cached in the constructor: the reference's downsampled Y/I/Q, phase congruency (float64),
    gradient magnitude, the log-Gabor filter bank and noise constants for the size, and the
    square roots of the reference's normalized region histograms. Candidates are processed one
    image at a time inside :meth:`evaluate` (that keeps the working set in cache, which is
    faster than wide batches; one planar float32 copy serves both terms); the result for a
    candidate does not depend on the batch it is in. Not thread-safe (work buffers are
    reused): use one instance per thread.

    Examples
    --------
    >>> ref = ThetaReference(real_frame_rgb)                         # doctest: +SKIP
    >>> scores = ref.evaluate(candidates)    # (N, H, W, 3) float32   # doctest: +SKIP
    >>> scores.theta, scores.theta1, scores.theta2                   # doctest: +SKIP
    """

    def __init__(
        self,
        reference,
        *,
        channels: str = "HSV",
        regions: int = 10,
        bins=None,
        mask=None,
        hist_mask=None,
        dtype=np.float32,
        workers=None,
    ):
        check_image(reference, "reference")
        if reference.ndim != 3:
            raise ValueError(f"reference must be an RGB image (H, W, 3), got shape {reference.shape}")
        self.shape = reference.shape
        self._fsim = FSIMReference(reference, mask=mask, dtype=dtype, workers=workers)
        if hist_mask is None or (isinstance(hist_mask, np.ndarray) and hist_mask.ndim == 2):
            hist_masks = [mask if hist_mask is None else hist_mask]
        else:
            hist_masks = list(hist_mask)
            if not hist_masks:
                raise ValueError("hist_mask is an empty sequence")
        self._hists = [HistogramReference(reference, channels=channels, regions=regions, bins=bins, mask=m)
                       for m in hist_masks]
        self._hist = self._hists[0]
        # Several disjoint masks (the backward fit's panel / water): one HSV pass over all pixels for all of them.
        self._split = None
        if len(hist_masks) > 1 and all(m is not None for m in hist_masks):
            try:
                self._split = SplitHistogramReference(reference, hist_masks, channels=channels, regions=regions,
                                                      bins=bins)
            except ValueError:      # overlapping masks: one pass per mask
                self._split = None
        self._fsim_planar_shape = (3,) + reference.shape[:2]

    def fork(self) -> "ThetaReference":
        """A copy for another thread: shares every cached reference array (read-only), has its own work buffers.

        Scores are those of this instance, bit for bit; building it costs no reference work.
        """
        import copy

        twin = copy.copy(self)
        twin._fsim = copy.copy(self._fsim)
        twin._fsim._buf = None
        twin._hists = [copy.copy(h) for h in self._hists]
        for h in twin._hists:
            h._ws = {}
        twin._hist = twin._hists[0]
        twin._split = None if self._split is None else self._split.fork()
        return twin

    @property
    def channels(self) -> str:
        """HSV channels used by theta_2."""
        return self._hist.channels

    def _batch(self, candidates) -> np.ndarray:
        if not isinstance(candidates, np.ndarray):
            raise TypeError(f"candidates must be a numpy array, got {type(candidates).__name__}")
        if candidates.ndim == 3:
            candidates = candidates[None]
        if candidates.ndim != 4 or candidates.shape[1:] != self.shape:
            raise ValueError(
                f"candidates must have shape (N, {', '.join(map(str, self.shape))}) or {self.shape}, "
                f"got {candidates.shape}"
            )
        if candidates.shape[0] == 0:
            raise ValueError("candidates is an empty stack")
        check_image(candidates, "candidates", allow_batch=True, values=False)  # dtype, sizes
        return candidates

    def evaluate(self, candidates) -> ThetaScores:
        """theta, theta_1 (FSIMc) and theta_2 of each candidate.

        Parameters
        ----------
        candidates : ndarray, shape (N, H, W, 3) or (H, W, 3)
            Simulated RGB images, uint8 or float in 0..255 (any is converted to a planar
            float32 working copy, one image at a time).

        Returns
        -------
        ThetaScores
            ``theta = (theta1 + theta2) / 2``, each of shape (N,).
        """
        batch = self._batch(candidates)
        n = batch.shape[0]
        t1 = np.empty(n)
        t2 = np.empty(n)
        shared = self._fsim.dtype == np.float32
        for k in range(n):
            img = batch[k]
            planes = self._hist.to_planar(img)  # float32 (3, H * W), shared by both terms
            if img.dtype != np.uint8:
                check_values(planes, f"candidates[{k}]")  # finite, in 0..255
            if shared:
                t1[k] = self._fsim.score_planar(planes.reshape(self._fsim_planar_shape))[1]
            else:
                t1[k] = self._fsim.score_planar(self._fsim.to_planar(img))[1]
            t2[k] = self._theta2(planes)
        return ThetaScores((t1 + t2) / 2.0, t1, t2)

    def score(self, candidates) -> np.ndarray:
        """theta of each candidate, shape (N,) (see :meth:`evaluate`)."""
        return self.evaluate(candidates).theta

    def score_planar(self, planes: np.ndarray) -> float:
        """theta of one candidate given as planar float32 ``(3, H * W)`` in 0..255 (an optimizer's inner
        loop: no interleaved copy). The same value as :meth:`score` of the same image, bit for bit."""
        if not isinstance(planes, np.ndarray) or planes.dtype != np.float32 \
                or planes.shape != (3, self.shape[0] * self.shape[1]) or not planes.flags.c_contiguous:
            raise ValueError(f"planes must be a C-contiguous float32 array of shape "
                             f"(3, {self.shape[0] * self.shape[1]})")
        check_values(planes, "candidate")  # finite, in 0..255
        if self._fsim.dtype == np.float32:
            t1 = self._fsim.score_planar(planes.reshape(self._fsim_planar_shape))[1]
        else:
            t1 = self._fsim.score_planar(planes.reshape(self._fsim_planar_shape).astype(self._fsim.dtype))[1]
        return (t1 + self._theta2(planes)) / 2.0

    def _theta2(self, planes: np.ndarray) -> float:
        """theta_2 of planar float32 ``(3, H * W)``: the mean over the histogram masks."""
        if self._split is not None:
            return sum(self._split.scores_planar(planes)) / len(self._hists)
        return sum(h.score_planar(planes) for h in self._hists) / len(self._hists)


def mean_theta(references: Sequence, candidate_stacks: Sequence, **kwargs) -> np.ndarray:
    """theta averaged over K reference frames.

    Parameters
    ----------
    references : sequence of ThetaReference or of RGB arrays, length K
        One per real frame. Prefer :class:`ThetaReference` objects built once: arrays are
        turned into new ones on every call (with ``kwargs``), redoing the reference work.
    candidate_stacks : sequence of ndarray, length K
        ``candidate_stacks[k]`` has shape (N, H_k, W_k, 3): candidate ``n`` (one parameter
        vector) simulated at frame ``k``'s pose. N must be the same for all frames.

    Returns
    -------
    ndarray, shape (N,)
        ``mean_k theta(reference_k, candidate_stacks[k][n])``.
    """
    refs = list(references)
    stacks = list(candidate_stacks)
    if not refs:
        raise ValueError("references is empty")
    if len(refs) != len(stacks):
        raise ValueError(f"got {len(refs)} references but {len(stacks)} candidate stacks")
    total = None
    for k, (ref, stack) in enumerate(zip(refs, stacks)):
        if not isinstance(ref, ThetaReference):
            ref = ThetaReference(ref, **kwargs)
        theta = ref.score(stack)
        if total is None:
            total = theta.copy()
        elif theta.shape != total.shape:
            raise ValueError(
                f"candidate stack {k} has {theta.shape[0]} candidates, stack 0 has {total.shape[0]}"
            )
        else:
            total += theta
    return total / len(refs)
