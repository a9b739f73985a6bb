"""theta_2: Bhattacharyya distance, HSV conventions, constructed histograms, bad input."""

import cv2
import numpy as np
import pytest
from PIL import Image

from datapaths import TEST_DATA
from uw_sil.metrics.histsim import (
    DEFAULT_BINS,
    HistogramReference,
    bhattacharyya_distance,
    hsv_histogram_similarity,
    rgb_to_hsv,
)

UW = TEST_DATA / "real_underwater"


# ---------------------------------------------------------------------------------------------
# Bhattacharyya distance
# ---------------------------------------------------------------------------------------------
def test_bhattacharyya_known_values():
    assert bhattacharyya_distance([1, 0], [0, 1]) == pytest.approx(1.0)
    assert bhattacharyya_distance([3, 1, 2], [3, 1, 2]) == pytest.approx(0.0, abs=1e-7)
    assert bhattacharyya_distance([0.5, 0.5], [1, 0]) == pytest.approx(np.sqrt(1 - np.sqrt(0.5)))
    # unnormalized counts are normalized; several histograms along an axis
    d = bhattacharyya_distance([[10, 10], [1, 3]], [[40, 0], [3, 1]])
    np.testing.assert_allclose(d, [np.sqrt(1 - np.sqrt(0.5)), np.sqrt(1 - 2 * np.sqrt(3 / 16))])


def test_bhattacharyya_matches_opencv():
    rng = np.random.default_rng(0)
    for _ in range(5):
        p = rng.integers(0, 50, size=32).astype(np.float32)
        q = rng.integers(0, 50, size=32).astype(np.float32)
        want = cv2.compareHist(p, q, cv2.HISTCMP_BHATTACHARYYA)
        assert bhattacharyya_distance(p, q) == pytest.approx(want, abs=1e-6)


@pytest.mark.parametrize(
    "p, q, msg",
    [([1, 2], [1, 2, 3], "same shape"), ([-1, 2], [1, 2], "non-negative"), ([0, 0], [1, 2], "zero"),
     ([np.nan, 1], [1, 2], "NaN"), ([], [], "empty")],
)
def test_bhattacharyya_bad_input(p, q, msg):
    with pytest.raises(ValueError, match=msg):
        bhattacharyya_distance(p, q)


# ---------------------------------------------------------------------------------------------
# HSV conventions
# ---------------------------------------------------------------------------------------------
def test_rgb_to_hsv_matches_opencv_float():
    x = np.random.default_rng(1).integers(0, 256, size=(40, 50, 3)).astype(np.uint8)
    x[0, :3] = [[10, 10, 10], [0, 0, 0], [255, 0, 255]]
    h, s, v = rgb_to_hsv(x)
    o = cv2.cvtColor(x.astype(np.float32), cv2.COLOR_RGB2HSV)  # H in degrees, S in 0..1
    np.testing.assert_allclose(h, o[..., 0], atol=1e-4)
    np.testing.assert_allclose(s, o[..., 1], atol=1e-6)
    np.testing.assert_array_equal(v, o[..., 2])
    assert h[0, 0] == 0 and h[0, 1] == 0 and h[0, 2] == 300  # achromatic -> 0 like OpenCV


def _reference_counts(img, regions, bins):
    """Slow, independent binning from rgb_to_hsv (float64) following the documented rules."""
    h, s, v = rgb_to_hsv(img)
    rows, cols = img.shape[:2]
    rb = np.floor(np.arange(rows) * regions / rows).astype(int)
    cb = np.floor(np.arange(cols) * regions / cols).astype(int)
    reg = rb[:, None] * regions + cb[None, :]
    out = {}
    codes = {
        "H": np.floor(h / (360 / bins["H"]) + 0.5).astype(int) % bins["H"],
        "S": np.minimum(np.floor(s * bins["S"]), bins["S"] - 1).astype(int),
        "V": np.floor(v * bins["V"] / 256).astype(int),
    }
    for c, code in codes.items():
        hist = np.zeros((regions * regions, bins[c]), int)
        np.add.at(hist, (reg.ravel(), code.ravel()), 1)
        out[c] = hist
    return out


def test_fast_histograms_match_slow_binning():
    img = np.array(Image.open(UW / "euvp_funiegan_testA" / "7.jpg"))
    ref = HistogramReference(img, regions=7)
    fast = ref._histograms(img)
    slow = _reference_counts(img, 7, DEFAULT_BINS)
    for c in "HSV":
        # float32 vs float64 can only disagree for values exactly on a bin edge
        assert np.abs(fast[c] - slow[c]).sum() <= 2e-4 * img.shape[0] * img.shape[1], c
        assert fast[c].sum() == img.shape[0] * img.shape[1]


def _hue_pixel(deg):
    """A fully saturated RGB pixel (float) of hue ``deg`` with V = 255."""
    h6 = (deg % 360) / 60.0
    x = 255.0 * (1 - abs(h6 % 2 - 1))
    table = [(255, x, 0), (x, 255, 0), (0, 255, x), (0, x, 255), (x, 0, 255), (255, 0, x)]
    return np.array(table[int(h6) % 6], float)


def test_hue_is_circular():
    def img(deg):
        return np.tile(_hue_pixel(deg), (20, 20, 1))

    assert rgb_to_hsv(_hue_pixel(358.0))[0] == pytest.approx(358.0)
    # 358 and 2 degrees share the red bin (centred on 0); 350 and 10 do not (10-degree bins)
    assert hsv_histogram_similarity(img(358), img(2), channels="H", regions=2) == 1.0
    assert hsv_histogram_similarity(img(350), img(10), channels="H", regions=2) == 0.0
    assert hsv_histogram_similarity(img(184), img(176), channels="H", regions=2) == 1.0


# ---------------------------------------------------------------------------------------------
# theta_2 on constructed histograms
# ---------------------------------------------------------------------------------------------
def _constructed_pair():
    """Grey 100x100 images: in 10x10 region r, r of its 100 pixels go from V=100 to V=200."""
    ref = np.full((100, 100, 3), 100, np.uint8)
    cand = ref.copy()
    for r in range(100):
        i, j = divmod(r, 10)
        block = cand[10 * i : 10 * i + 10, 10 * j : 10 * j + 10].reshape(100, 3)
        block[:r] = 200
        cand[10 * i : 10 * i + 10, 10 * j : 10 * j + 10] = block.reshape(10, 10, 3)
    # per region: p = delta(bin 12), q = (1 - f) delta(12) + f delta(25), f = r/100
    d = np.sqrt(1 - np.sqrt(1 - np.arange(100) / 100))
    return ref, cand, d


def test_theta2_on_constructed_histograms():
    ref, cand, d = _constructed_pair()
    med = (d[49] + d[50]) / 2  # median of 100 regions: mean of the two middle ones
    assert hsv_histogram_similarity(ref, cand, channels="V") == pytest.approx(1 - med, abs=1e-12)
    # grey pixels: H and S agree (bin 0), so the channel mean divides d_V by 3 (Eq. 3: mean)
    assert hsv_histogram_similarity(ref, cand) == pytest.approx(1 - med / 3, abs=1e-12)
    dist = HistogramReference(ref, channels="V").distances(cand)
    np.testing.assert_allclose(dist, d, atol=1e-12)
    # identical histograms -> 1, float or uint8 alike
    assert hsv_histogram_similarity(ref, ref) == 1.0
    assert hsv_histogram_similarity(cand, cand.astype(np.float32)) == 1.0


def test_channel_selection_colour_vs_luminance():
    img = np.array(Image.open(UW / "euvp_funiegan_testA" / "12.jpg"))
    swapped = img[..., [1, 0, 2]]  # swap R and G: same S and V everywhere, different hue
    assert hsv_histogram_similarity(img, swapped, channels="V") == 1.0
    assert hsv_histogram_similarity(img, swapped, channels="sv") == 1.0
    assert hsv_histogram_similarity(img, swapped, channels="H") < 0.9
    darker = (img * 0.6).astype(np.uint8)
    assert hsv_histogram_similarity(img, darker, channels="V") < hsv_histogram_similarity(img, darker, channels="H")


def test_theta2_bounded_and_decreasing_with_colour_cast():
    img = np.array(Image.open(UW / "euvp_funiegan_testA" / "3.jpg")).astype(np.float32)
    vals = []
    for k in (0.0, 10.0, 25.0, 60.0):
        cast = np.clip(img + np.array([-k, 0.0, k], np.float32), 0, 255)
        vals.append(hsv_histogram_similarity(img.astype(np.uint8), cast))
    assert vals[0] == 1.0 and all(0 <= v <= 1 for v in vals)
    assert vals[0] > vals[1] > vals[2] > vals[3]


def test_reference_batch_and_mask():
    img = np.array(Image.open(UW / "euvp_funiegan_testA" / "1.jpg"))
    rng = np.random.default_rng(0)
    cands = np.clip(img[None] + rng.normal(0, 20, (3,) + img.shape), 0, 255).astype(np.float32)
    ref = HistogramReference(img)
    batch = ref.score(cands)
    np.testing.assert_array_equal(batch, [ref.score(c)[0] for c in cands])
    np.testing.assert_array_equal(batch, [hsv_histogram_similarity(img, c) for c in cands])
    mask = np.zeros(img.shape[:2], bool)
    mask[:128] = True  # top half: regions 0..49 (256 rows, 10 regions)
    changed = cands[0].copy()
    changed[128:] = 0.0  # outside the mask
    mref = HistogramReference(img, mask=mask)
    assert mref.score(changed)[0] == mref.score(cands[0])[0]
    assert np.isnan(mref.distances(cands[0])[60])  # a region without masked pixels
    assert np.array_equal(HistogramReference(img, mask=np.ones(img.shape[:2], bool)).score(cands), batch)


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------
IMG = np.zeros((20, 30, 3), np.uint8)


@pytest.mark.parametrize(
    "kwargs, exc, msg",
    [
        (dict(channels="HX"), ValueError, "subset"),
        (dict(channels=""), ValueError, "subset"),
        (dict(channels="HH"), ValueError, "repeats"),
        (dict(channels=["H"]), TypeError, "string"),
        (dict(regions=0), ValueError, "positive"),
        (dict(regions=25), ValueError, "too small"),
        (dict(bins=1), ValueError, "bins"),
        (dict(bins="36"), TypeError, "bins"),
        (dict(mask=np.ones((20, 30))), TypeError, "boolean"),
        (dict(mask=np.ones((20, 31), bool)), ValueError, "shape"),
        (dict(mask=np.zeros((20, 30), bool)), ValueError, "no pixel"),
    ],
)
def test_bad_parameters(kwargs, exc, msg):
    with pytest.raises(exc, match=msg):
        hsv_histogram_similarity(IMG, IMG, **kwargs)


def test_bad_images():
    with pytest.raises(ValueError, match="same shape"):
        hsv_histogram_similarity(IMG, IMG[:, :29])
    with pytest.raises(ValueError, match="RGB"):
        HistogramReference(IMG[..., 0])
    with pytest.raises(ValueError, match="NaN"):
        hsv_histogram_similarity(IMG, np.full(IMG.shape, np.nan))
    with pytest.raises(TypeError, match="dtype"):
        hsv_histogram_similarity(IMG, IMG.astype(np.int64))
    with pytest.raises(ValueError, match="image shape"):
        HistogramReference(IMG).score(np.zeros((2, 20, 31, 3), np.uint8))
