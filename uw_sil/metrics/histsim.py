"""HSV region-histogram similarity theta_2 (paper Sec. 3.3, Eq. 3, turned into a similarity).

Both images are split into ``regions x regions`` rectangles; in every region the histogram of
each selected HSV channel is compared with the Bhattacharyya distance, the distances are
averaged over the channels and the median is taken over the regions (Eq. 3). Here

    theta_2 = 1 - median_r mean_{c in C} d_B(h_c^r(ref), h_c^r(cand)),

a similarity in [0, 1] (1 = identical histograms in at least half of the regions); why it differs
from the paper's distance: :func:`hsv_histogram_similarity`, Notes.

Colour conventions (float computation, no 8-bit quantisation of H/S/V):

* V = max(R, G, B) in 0..255; S = (V - min(R, G, B)) / V (0 where V = 0), in [0, 1];
* H in degrees [0, 360) from the usual hexcone formula (OpenCV's float ``RGB2HSV``; its 8-bit
  hue is this value halved, 0..179); achromatic pixels (max = min) get H = 0 like OpenCV.
* Default bins: H 36 (10 degrees, i.e. 5 levels of OpenCV's 8-bit hue), S 32, V 32 (8 grey
  levels each). Hue is circular: bin ``k`` covers ``[(k - 1/2) w, (k + 1/2) w)`` modulo 360
  with ``w = 360 / bins``, so the reds around 0/360 degrees share bin 0 instead of being split
  between the first and the last bin.
* Regions: pixel row ``i`` lies in region row ``floor(i * regions / H)`` (columns alike), so
  regions differ in size by at most one row/column when ``H`` is not a multiple.

References
----------
.. [1] T. Doernbach, A. Gomez Chavez, C. A. Mueller and A. Birk, "High-Fidelity Deep-Sea Perception
   Using Simulation in the Loop", IFAC conference paper, 2018 (Sec. 3.3, Eq. 3). ("the paper"
   throughout uw_sil.)
.. [2] A. Bhattacharyya, "On a measure of divergence between two statistical populations defined by
   their probability distributions", Bull. Calcutta Math. Soc. 35, 99-109, 1943 (d_B).
"""
from __future__ import annotations

import numpy as np

from .._shared.checks import check_image, check_mask

__all__ = [
    "DEFAULT_BINS",
    "HistogramReference",
    "SplitHistogramReference",
    "bhattacharyya_distance",
    "hsv_histogram_similarity",
    "rgb_to_hsv",
]

#: Default number of bins per channel.
DEFAULT_BINS = {"H": 36, "S": 32, "V": 32}


def _parse_channels(channels) -> str:
    if not isinstance(channels, str):
        raise TypeError(f"channels must be a string such as 'HSV', 'HS' or 'V', got {type(channels).__name__}")
    chans = channels.upper()
    if not chans or any(c not in "HSV" for c in chans) or len(set(chans)) != len(chans):
        raise ValueError(f"channels must be a non-empty subset of 'HSV' without repeats, got {channels!r}")
    return "".join(c for c in "HSV" if c in chans)


def _parse_bins(bins, chans: str) -> dict:
    if bins is None:
        return {c: DEFAULT_BINS[c] for c in chans}
    if isinstance(bins, (int, np.integer)):
        out = {c: int(bins) for c in chans}
    elif isinstance(bins, dict):
        out = {c: int(bins.get(c, DEFAULT_BINS[c])) for c in chans}
    else:
        raise TypeError(f"bins must be None, an int or a dict like {{'H': 36}}, got {type(bins).__name__}")
    for c, nb in out.items():
        if not 2 <= nb <= 4096:
            raise ValueError(f"bins for channel {c} must be in 2..4096, got {nb}")
    return out


def rgb_to_hsv(rgb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hue, saturation and value of RGB pixels (float, no quantisation).

    Parameters
    ----------
    rgb : ndarray, shape (..., 3)
        RGB values in 0..255 (uint8 or float).

    Returns
    -------
    h : ndarray
        Hue in degrees, [0, 360); 0 for achromatic pixels (OpenCV convention).
    s : ndarray
        Saturation ``(max - min) / max`` in [0, 1]; 0 where max = 0.
    v : ndarray
        Value ``max(R, G, B)`` in 0..255.
    """
    x = np.asarray(rgb)
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ValueError(f"rgb must have a last axis of length 3, got shape {x.shape}")
    x = x.astype(np.float64)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    v = np.maximum(np.maximum(r, g), b)
    d = v - np.minimum(np.minimum(r, g), b)
    s = np.divide(d, v, out=np.zeros_like(v), where=v > 0)
    h6 = _hue_sextant(r, g, b, v, d)
    h = 60.0 * h6
    h = np.where(h < 0, h + 360.0, h)
    return h, s, v


def _hue_sextant(r, g, b, v, d):
    """Hue in sextants, [-1, 5): (G - B)/d if V = R, 2 + (B - R)/d if V = G, else 4 + (R - G)/d."""
    num = np.where(v == r, g - b, np.where(v == g, (b - r) + 2 * d, (r - g) + 4 * d))
    return np.divide(num, d, out=np.zeros_like(num), where=d > 0)


def _hue_sextant_fast(r, g, b, v, d, out, w1, w2, m1, m2):
    """:func:`_hue_sextant` for float32 planes, branch-free, into preallocated buffers.

    ``np.where`` on the case masks is several times slower (branch mispredictions), so the
    three cases are selected by 0/1 factors; the first matching case wins (V = R, then V = G,
    then B) as in OpenCV; 0 where d = 0. ``out``, ``w1``, ``w2`` are float32 and ``m1``,
    ``m2`` bool work buffers of the planes' size.
    """
    f32 = np.float32
    is_r, is_g = w1, w2
    np.equal(v, r, out=m1)
    np.copyto(is_r, m1)
    np.equal(v, g, out=m2)
    np.copyto(is_g, m2)
    np.multiply(is_g, is_r, out=out)
    is_g -= out  # V = G but not V = R
    np.subtract(g, b, out=out)
    out *= is_r  # case R: (G - B)
    # case G: 2 d + B - R, weight is_g; case B: 4 d + R - G, weight 1 - is_r - is_g
    np.multiply(d, f32(2.0), out=is_r)  # is_r is no longer needed as such: reuse
    is_r += b
    is_r -= r
    is_r *= is_g
    out += is_r
    np.multiply(d, f32(4.0), out=is_r)
    is_r += r
    is_r -= g
    # weight of case B: (v != r) & (v != g)
    np.logical_or(m1, m2, out=m1)
    np.logical_not(m1, out=m1)
    np.copyto(is_g, m1)
    is_r *= is_g
    out += is_r
    np.maximum(d, f32(1e-30), out=is_r)  # d = 0 -> all equal -> numerator 0
    out /= is_r
    return out


def bhattacharyya_distance(p, q, axis: int = -1) -> np.ndarray:
    """Bhattacharyya distance of two histograms (the Hellinger form used by OpenCV).

    Parameters
    ----------
    p, q : array_like
        Non-negative histograms of the same shape; each is normalized to sum 1 along ``axis``.
    axis : int
        Axis holding the bins.

    Returns
    -------
    ndarray
        ``d_B = sqrt(1 - sum_b sqrt(p_b q_b))`` in [0, 1] (``cv2.HISTCMP_BHATTACHARYYA``):
        0 for equal histograms, 1 for disjoint supports.

    References
    ----------
    .. [1] A. Bhattacharyya, "On a measure of divergence between two statistical populations
       defined by their probability distributions", Bull. Calcutta Math. Soc. 35, 1943.
    """
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    if p.shape != q.shape:
        raise ValueError(f"p and q must have the same shape, got {p.shape} and {q.shape}")
    if p.size == 0:
        raise ValueError("histograms are empty")
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise ValueError("histograms contain NaN or inf")
    if (p < 0).any() or (q < 0).any():
        raise ValueError("histograms must be non-negative")
    sp, sq = p.sum(axis=axis, keepdims=True), q.sum(axis=axis, keepdims=True)
    if (sp == 0).any() or (sq == 0).any():
        raise ValueError("a histogram sums to zero")
    bc = np.sqrt(p / sp * (q / sq)).sum(axis=axis)
    return np.sqrt(np.clip(1.0 - bc, 0.0, 1.0))


class HistogramReference:
    """theta_2 of many candidate images against one reference image (reference cached).

    Parameters
    ----------
    reference : ndarray, shape (H, W, 3)
        RGB reference image, uint8 or float in 0..255, at least ``regions`` pixels per side.
    channels : str
        Subset of ``"HSV"`` (any order/case): ``"HSV"`` all, ``"HS"`` colour only, ``"V"``
        luminance only (the paper's "set focus on color or luminance", Sec. 3.3).
    regions : int
        The image is split into ``regions x regions`` rectangles (paper: 10).
    bins : None, int or dict
        Bins per channel; ``None`` = :data:`DEFAULT_BINS` (H 36, S 32, V 32); an int for all
        channels; a dict overriding some channels.
    mask : ndarray of bool, shape (H, W), optional
        Only these pixels are counted (in both images). Regions without any masked pixel are
        left out of the median.

    Notes
    -----
    The reference's normalized histograms (their square roots) are computed once; scoring a
    candidate costs one HSV conversion and one ``bincount`` per channel.
    """

    def __init__(self, reference, *, channels: str = "HSV", regions: int = 10, bins=None, mask=None):
        check_image(reference, "reference")
        if reference.ndim != 3:
            raise ValueError(f"reference must be an RGB image (H, W, 3), got shape {reference.shape}")
        self.channels = _parse_channels(channels)
        self.bins = _parse_bins(bins, self.channels)
        if isinstance(regions, bool) or not isinstance(regions, (int, np.integer)) or regions < 1:
            raise ValueError(f"regions must be a positive integer, got {regions!r}")
        rows, cols = reference.shape[:2]
        if rows < regions or cols < regions:
            raise ValueError(f"image {rows}x{cols} is too small for {regions}x{regions} regions")
        self.regions = int(regions)
        self.shape = reference.shape
        rb = (np.arange(rows) * regions) // rows  # region row of each pixel row
        cb = (np.arange(cols) * regions) // cols
        region = (rb[:, None] * regions + cb[None, :]).astype(np.intp)
        if mask is None:
            self._sel = None
            self._region = region.ravel()
        else:
            m = check_mask(mask, (rows, cols))
            if not m.any():
                raise ValueError("mask selects no pixel")
            self._sel = np.flatnonzero(m)
            self._region = region.ravel()[self._sel]
        n_reg = regions * regions
        self._slots = n_reg     # rows of the (slot, bin) histograms: the regions
        counts = np.bincount(self._region, minlength=n_reg).astype(np.float64)
        self._valid = counts > 0
        self._inv_counts = np.divide(1.0, counts, out=np.zeros_like(counts), where=self._valid)
        # per channel: offset of each pixel's region in the flattened (region, bin) histogram
        self._offsets = {c: self._region * self.bins[c] for c in self.channels}
        self._ws = {}
        ref_hist = self._histograms(reference)
        self._sqrt_ref = {c: np.sqrt(ref_hist[c] * self._inv_counts[:, None]) for c in self.channels}

    def _work(self, npix: int, planes: bool = True) -> dict:
        """Work buffers reused between calls (fresh large arrays cost page faults each time).

        Not thread-safe: use one instance per thread.
        """
        key = "planes" if planes else "work"
        ws = self._ws.get(key)
        if ws is None or ws["n"] != npix:
            if planes:
                ws = {"n": npix, "planes": np.empty((3, npix), np.float32)}
            else:
                ws = {k: np.empty(npix, np.float32) for k in ("v", "d", "t", "w1", "w2")}
                ws.update(n=npix, idx=np.empty(npix, np.intp), m1=np.empty(npix, bool), m2=np.empty(npix, bool))
                ws["sel"] = np.empty((3, npix), np.float32) if self._sel is not None else None
            self._ws[key] = ws
        return ws

    def to_planar(self, img: np.ndarray) -> np.ndarray:
        """Planar float32 copy ``(3, H * W)`` of a validated RGB image, in a reused buffer (overwritten by
        the next call; public for criteria sharing one copy, as :class:`uw_sil.metrics.theta.ThetaReference`)."""
        rows, cols = img.shape[:2]
        ws = self._work(rows * cols)
        np.copyto(ws["planes"].reshape(3, rows, cols), np.moveaxis(img, -1, 0), casting="unsafe")
        return ws["planes"]

    def _histograms(self, img: np.ndarray) -> dict:
        """Per channel histogram counts, shape (regions**2, bins), of one RGB image."""
        return self._histograms_planar(self.to_planar(img))

    def _histograms_planar(self, planes: np.ndarray) -> dict:
        """Histograms from planar float32 RGB ``(3, H * W)`` (all pixels, the mask is applied here).

        Float32 arithmetic in reused buffers; same bins as :func:`rgb_to_hsv` followed by the
        binning rules of the module notes.
        """
        ws = self._work(planes.shape[1] if self._sel is None else self._sel.size, planes=False)
        if self._sel is not None:
            planes = np.take(planes, self._sel, axis=1, out=ws["sel"])
        r, g, b = planes
        v, d, t, idx = ws["v"], ws["d"], ws["t"], ws["idx"]
        np.maximum(r, g, out=v)
        np.maximum(v, b, out=v)
        np.minimum(r, g, out=d)
        np.minimum(d, b, out=d)
        np.subtract(v, d, out=d)  # max - min
        f32 = np.float32
        n_reg = self._slots
        out = {}
        for c in self.channels:
            nb = self.bins[c]
            if c == "V":
                np.multiply(v, f32(nb / 256.0), out=t)  # v <= 255 -> t < nb
            elif c == "S":
                # floor(nb * d / v), 0 where v = 0 (then d = 0 too); clamp S = 1 into the last bin
                np.maximum(v, f32(1e-30), out=t)
                np.divide(d, t, out=t)
                t *= f32(nb)
                np.minimum(t, f32(nb - 1), out=t)
            else:
                w1, w2 = ws["w1"], ws["w2"]
                m1 = ws["m1"]
                _hue_sextant_fast(r, g, b, v, d, t, w1, w2, m1, ws["m2"])  # [-1, 5)
                np.less(t, 0, out=m1)
                np.copyto(w1, m1)
                w1 *= f32(6.0)
                t += w1  # [0, 6)
                t *= f32(nb / 6.0)
                t += f32(0.5)  # bin k centred on k * 360 / nb degrees
                np.greater_equal(t, nb, out=m1)
                np.copyto(w1, m1)
                w1 *= f32(nb)
                t -= w1  # circular: [nb - 1/2, nb + 1/2) -> bin 0
            np.copyto(idx, t, casting="unsafe")  # t >= 0: truncation is floor
            idx += self._offsets[c]
            out[c] = np.bincount(idx, minlength=n_reg * nb).reshape(n_reg, nb)
        return out

    def distances(self, candidate: np.ndarray) -> np.ndarray:
        """Channel-mean Bhattacharyya distance per region, shape (regions**2,); NaN if no pixel.

        ``candidate`` is an RGB image ``(H, W, 3)`` like the reference (validated by the caller).
        """
        return self._distances(self._histograms(candidate))

    def _distances(self, hist: dict) -> np.ndarray:
        acc = np.zeros(self.regions * self.regions)
        for c in self.channels:
            bc = (np.sqrt(hist[c] * self._inv_counts[:, None]) * self._sqrt_ref[c]).sum(axis=1)
            acc += np.sqrt(np.clip(1.0 - bc, 0.0, 1.0))
        acc /= len(self.channels)
        acc[~self._valid] = np.nan
        return acc

    def _score_one(self, candidate: np.ndarray) -> float:
        return self.score_planar(self.to_planar(candidate))

    def score_planar(self, planes: np.ndarray) -> float:
        """theta_2 of one validated candidate given as planar float32 ``(3, H * W)``."""
        d = self._distances(self._histograms_planar(planes))[self._valid]
        return 1.0 - float(np.median(d))

    def score(self, candidates) -> np.ndarray:
        """theta_2 of each candidate.

        Parameters
        ----------
        candidates : ndarray, shape (N, H, W, 3) or (H, W, 3)
            RGB, uint8 or float in 0..255, same size as the reference.

        Returns
        -------
        ndarray, shape (N,)
            ``1 - median_r mean_c d_B``, in [0, 1].
        """
        check_image(candidates, "candidates", allow_batch=True)
        if candidates.ndim == 2:
            raise ValueError(f"candidates must be RGB, got shape {candidates.shape}")
        batch = candidates[None] if candidates.ndim == 3 else candidates
        if batch.shape[1:] != self.shape:
            raise ValueError(f"candidates have image shape {batch.shape[1:]}, reference has {self.shape}")
        return np.array([self._score_one(c) for c in batch])


class SplitHistogramReference:
    """theta_2 over several disjoint pixel sets of one image (e.g. the panel and the water), in one pass.

    The same values, bit for bit, as one :class:`HistogramReference` per mask (``parts``), whose histograms
    take each set's pixels out of the image first: here the HSV bins are computed once over all pixels and
    counted into one histogram with a (set, region) row per pixel (pixels of no set into a spare row).

    Parameters
    ----------
    reference : ndarray, shape (H, W, 3)
    masks : sequence of ndarray of bool, shape (H, W)
        Disjoint pixel sets (ValueError if two share a pixel).
    channels, regions, bins : as :class:`HistogramReference`.
    """

    def __init__(self, reference, masks, *, channels: str = "HSV", regions: int = 10, bins=None):
        masks = list(masks)
        if not masks:
            raise ValueError("masks is empty")
        self.parts = [HistogramReference(reference, channels=channels, regions=regions, bins=bins, mask=m)
                      for m in masks]
        self._all = HistogramReference(reference, channels=channels, regions=regions, bins=bins)
        self.channels, self.bins, self.shape = self._all.channels, self._all.bins, self._all.shape
        n_reg = self._all.regions ** 2
        k_none = len(masks)
        owner = np.full(self.shape[0] * self.shape[1], k_none, dtype=np.intp)
        for k, part in enumerate(self.parts):
            sel = np.arange(owner.size) if part._sel is None else part._sel
            if np.any(owner[sel] != k_none):
                raise ValueError("the masks overlap")
            owner[sel] = k
        self._n_reg = n_reg
        self._all._slots = (k_none + 1) * n_reg
        slot = owner * n_reg + self._all._region
        self._all._offsets = {c: slot * self.bins[c] for c in self.channels}

    def to_planar(self, img: np.ndarray) -> np.ndarray:
        """See :meth:`HistogramReference.to_planar`."""
        return self._all.to_planar(img)

    def scores_planar(self, planes: np.ndarray) -> list:
        """theta_2 of each set for one validated candidate given as planar float32 ``(3, H * W)``."""
        hist = self._all._histograms_planar(planes)
        n = self._n_reg
        out = []
        for k, part in enumerate(self.parts):
            d = part._distances({c: h[k * n:(k + 1) * n] for c, h in hist.items()})[part._valid]
            out.append(1.0 - float(np.median(d)))
        return out

    def fork(self) -> "SplitHistogramReference":
        """A copy with its own work buffers (for another thread), sharing the reference's arrays."""
        import copy

        twin = copy.copy(self)
        twin._all = copy.copy(self._all)
        twin._all._ws = {}
        return twin


def hsv_histogram_similarity(ref, cand, channels: str = "HSV", regions: int = 10, bins=None, mask=None) -> float:
    """theta_2: HSV region-histogram similarity of two RGB images (paper Eq. 3, corrected).

    Parameters
    ----------
    ref, cand : ndarray, shape (H, W, 3)
        RGB images (not OpenCV's BGR), uint8 or float in 0..255, same shape.
    channels : str
        Subset of ``"HSV"``; ``"HS"`` compares colour only, ``"V"`` luminance only.
    regions : int
        ``regions x regions`` rectangles (paper: 10).
    bins : None, int or dict
        Bins per channel (default H 36, S 32, V 32; see the module notes).
    mask : ndarray of bool, shape (H, W), optional
        Pixels to count.

    Returns
    -------
    float
        ``theta_2 = 1 - median_r mean_c d_B(h_c^r(ref), h_c^r(cand))`` in [0, 1]; 1 when the
        histograms agree in at least half of the regions.

    Notes
    -----
    Deviation from the paper: its Eq. 3 defines theta_2 as the median *distance* itself, Eq. 4
    averages it with the FSIMc *similarity* into theta, and Algorithm 1 keeps the agent of the
    largest theta (line 10), so as written the optimization rewards histograms that disagree. Here
    the distance is turned into a similarity ``1 - d``, so that maximizing theta makes them agree.
    Algorithm 1 (line 8) also takes the median over channels where Eq. 3 takes the mean: the mean of
    Eq. 3 is used. The paper says neither the bins nor the HSV scaling; ``d_B`` is
    :func:`bhattacharyya_distance` (OpenCV's ``HISTCMP_BHATTACHARYYA``). HSV is computed in float
    from the RGB values (no 8-bit quantisation), hue bins are centred on red (circular hue).

    References
    ----------
    .. [1] Doernbach et al. 2018 (see the module), Sec. 3.3, Eq. 3; Sec. 3.4, Eq. 4 and Algorithm 1.
    """
    check_image(ref, "ref")
    check_image(cand, "cand")
    if ref.shape != cand.shape:
        raise ValueError(f"ref and cand must have the same shape, got {ref.shape} and {cand.shape}")
    ref_hist = HistogramReference(ref, channels=channels, regions=regions, bins=bins, mask=mask)
    return ref_hist._score_one(cand)
