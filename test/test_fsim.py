"""FSIM / FSIMc: MATLAB reference values, MATLAB conventions, properties and bad input."""

import numpy as np
import pytest
from PIL import Image  # Pillow comes with matplotlib (an install requirement)
from scipy.ndimage import gaussian_filter
from scipy.signal import convolve2d

from datapaths import TEST_DATA, external_file
from uw_sil.metrics.fsim import (
    FSIMReference,
    _box_downsample,
    _chroma_term,
    _middle_order_stats,
    downsample_factor,
    fsim,
    phase_congruency,
)

DATA = TEST_DATA
IQA = DATA / "iqa_pairs"
UW = DATA / "real_underwater"


def _read(path):
    # GIFs have an identity grey palette: Pillow's "L"/"P" values are the grey levels MATLAB reads
    return np.array(Image.open(path))


@pytest.fixture(scope="module")
def tid_pair():
    return _read(IQA / "I01.BMP"), _read(IQA / "i01_01_5.bmp")


@pytest.fixture(scope="module")
def uw_image():
    return _read(UW / "suim_test" / "images" / "f_r_1965_.jpg")  # 640x480 RGB


# ---------------------------------------------------------------------------------------------
# Published MATLAB values (FeatureSIM.m)
# ---------------------------------------------------------------------------------------------
def test_goldhill_grey_matches_matlab():
    ref = _read(IQA / "goldhill.gif")
    dist = _read(IQA / "goldhill_jpeg.gif")
    assert ref.dtype == np.uint8 and ref.ndim == 2
    f, fc = fsim(ref, dist)
    assert abs(f - 0.89691) <= 6e-6
    assert fc == f  # grey images: FSIMc is FSIM


def test_tid2013_colour_matches_matlab(tid_pair):
    f, fc = fsim(*tid_pair)
    assert abs(f - 0.93674) <= 6e-6
    assert abs(fc - 0.92587) <= 6e-6


# MATLAB FeatureSIM.m FSIMc on the IQA-PyTorch calibration pairs, as published (4 decimals) in
# chaofengc/IQA-PyTorch ResultsCalibra/results_original_color.csv
CALIB_MATLAB_FSIMC = {"I03": 0.6890, "I04": 0.9702, "I06": 0.9927, "I08": 0.9575, "I19": 0.8220}


@pytest.mark.parametrize("name", sorted(CALIB_MATLAB_FSIMC))
def test_calibration_pairs_match_matlab_4_decimals(name):
    # Not in the repository (IQA-PyTorch's images are not under an Apache/MIT licence): see test/datapaths.py
    ref = _read(external_file(f"iqa_pairs/calib/ref/{name}.bmp"))
    dist = _read(external_file(f"iqa_pairs/calib/dist/{name}.bmp"))
    fc = fsim(ref, dist).fsimc
    assert abs(fc - CALIB_MATLAB_FSIMC[name]) <= 5e-5 + 1e-9


# ---------------------------------------------------------------------------------------------
# MATLAB conventions
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "shape, factor",
    [((480, 640), 2), ((640, 960), 3), ((384, 512), 2), ((383, 500), 1), ((128, 128), 1), ((1, 1), 1), ((1152, 2000), 5)],
)
def test_downsample_factor_uses_matlab_rounding(shape, factor):
    # 640/256 = 2.5 -> 3 (halves away from zero; Python's round would give 2)
    assert downsample_factor(*shape) == factor


def _matlab_conv_same_then_sample(x, f):
    """Independent emulation: full 2-D convolution, MATLAB's 'same' window, then 1:f:end."""
    full = convolve2d(x, np.ones((f, f)) / f**2, mode="full")
    start = f // 2  # MATLAB keeps the central part starting at floor(size(kernel)/2) + 1
    same = full[start : start + x.shape[0], start : start + x.shape[1]]
    return same[::f, ::f]


def test_matlab_same_convention_known_value():
    # MATLAB: conv([1 2 3], [1 1], 'same') = [3 5 3]
    x = np.array([[1.0, 2.0, 3.0]])
    full = convolve2d(x, np.ones((1, 2)), mode="full")
    assert np.array_equal(full[:, 1:4], [[3.0, 5.0, 3.0]])


@pytest.mark.parametrize("f", [2, 3, 4, 5])
@pytest.mark.parametrize("shape", [(17, 23), (16, 24), (20, 21), (9, 10)])
def test_box_downsample_matches_conv2_same(f, shape):
    x = np.random.default_rng(f).uniform(0, 255, size=shape)
    got = _box_downsample(x, f)
    want = _matlab_conv_same_then_sample(x, f)
    assert got.shape == (-(-shape[0] // f), -(-shape[1] // f))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)


def test_box_downsample_batched_and_channel_axes():
    x = np.random.default_rng(0).uniform(0, 255, size=(2, 11, 13, 3))
    got = _box_downsample(x, 3, axes=(1, 2))
    for n in range(2):
        for c in range(3):
            np.testing.assert_allclose(got[n, ..., c], _matlab_conv_same_then_sample(x[n, ..., c], 3), atol=1e-10)


def test_chroma_term_is_real_part_of_principal_power():
    si = np.array([0.9, -0.5, 0.3, -0.2, 0.0])
    sq = np.array([0.8, 0.7, -0.6, -0.9, 0.5])
    want = np.real((si * sq).astype(complex) ** 0.03)  # MATLAB real((SI.*SQ).^lambda)
    np.testing.assert_allclose(_chroma_term(si, sq), want, rtol=1e-14, atol=0)
    # and it is not abs(x)^0.03 for negative products
    assert _chroma_term(np.array([-0.5]), np.array([1.0]))[0] < 0.5**0.03 - 1e-3


@pytest.mark.parametrize("n", [1, 2, 7, 4096, 4097, 76800, 76801])
def test_middle_order_stats_give_numpy_median(n):
    rng = np.random.default_rng(n)
    rows = [rng.rayleigh(size=n), np.round(rng.uniform(0, 3, size=n)), np.full(n, 2.5), np.sort(np.abs(rng.normal(size=n)))]
    a = np.stack(rows).astype(np.float32)
    lo, hi = _middle_order_stats(a)
    np.testing.assert_array_equal((lo + hi) / 2, np.median(a.astype(np.float64), axis=1))
    # median of the squares uses the same order statistics (MATLAB: median(abs(EO).^2))
    np.testing.assert_allclose((lo * lo + hi * hi) / 2, np.median(a.astype(np.float64) ** 2, axis=1), rtol=1e-15)


def test_phase_congruency_properties():
    img = np.zeros((64, 80))
    img[:, 40:] = 100.0  # vertical step edge
    pc = phase_congruency(img)
    assert pc.shape == img.shape and np.isfinite(pc).all()
    assert pc.min() >= 0 and pc.max() <= 1
    assert pc[32, 39:41].min() > 0.7  # at the edge
    # the maxima are at the edge (columns 39/40) and at the circular wrap-around (0/79)
    assert set(np.argsort(pc[32])[-4:]) == {0, 39, 40, 79}
    assert pc[32, 15:25].max() < pc[32, 39:41].min() - 0.2
    # odd sizes use the (n-1) normalisation of phasecong2 and still work
    assert np.isfinite(phase_congruency(img[:63, :79])).all()
    # dimensionless: invariant to brightness offset, nearly so to contrast (epsilon = 1e-4)
    tex = np.random.default_rng(3).uniform(0, 100, size=(40, 50))
    np.testing.assert_allclose(phase_congruency(tex + 50), phase_congruency(tex), atol=1e-9)
    np.testing.assert_allclose(phase_congruency(2 * tex), phase_congruency(tex), atol=2e-3)
    # constant image: no phase structure -> 0 (MATLAB: 0/0)
    assert np.array_equal(phase_congruency(np.full((30, 40), 7.0)), np.zeros((30, 40)))


# ---------------------------------------------------------------------------------------------
# Properties
# ---------------------------------------------------------------------------------------------
def test_identity_is_one_and_symmetric(tid_pair):
    ref, dist = tid_pair
    assert fsim(ref, ref) == (1.0, 1.0)
    a, b = fsim(ref, dist), fsim(dist, ref)
    assert a.fsim == pytest.approx(b.fsim, abs=1e-12) and a.fsimc == pytest.approx(b.fsimc, abs=1e-12)
    # uint8 and float input give the same numbers
    assert fsim(ref.astype(np.float32), dist.astype(np.float64)) == pytest.approx(a, abs=1e-12)


@pytest.mark.parametrize("name", ["euvp_funiegan_testA/3.jpg", "suim_test/images/f_r_1965_.jpg"])
def test_monotone_and_bounded_under_blur_and_noise(name):
    img = _read(UW / name)
    x = img.astype(np.float64)
    blur = [fsim(img, np.clip(gaussian_filter(x, (s, s, 0)), 0, 255)) for s in (0.7, 1.5, 3.0)]
    noise = np.random.default_rng(0).normal(size=x.shape)
    noisy = [fsim(img, np.clip(x + s * noise, 0, 255)) for s in (3.0, 10.0, 30.0)]
    for seq in (blur, noisy):
        for k in (0, 1):  # FSIM and FSIMc
            vals = [r[k] for r in seq]
            assert all(0.0 <= v < 1.0 for v in vals)
            assert vals[0] > vals[1] > vals[2]


def test_constant_images_are_defined():
    c1 = np.full((40, 50, 3), 90, np.uint8)
    c2 = np.full((40, 50, 3), 140, np.uint8)
    assert fsim(c1, c1) == (1.0, 1.0)  # MATLAB: NaN (0/0)
    r = fsim(c1, c2)
    assert np.isfinite(r).all() and 0 < r.fsimc <= r.fsim <= 1
    tex = np.random.default_rng(0).integers(0, 256, size=(40, 50, 3)).astype(np.uint8)
    r = fsim(tex, c1)
    assert np.isfinite(r).all() and 0 <= r.fsimc <= 1


# ---------------------------------------------------------------------------------------------
# Cached reference / batches
# ---------------------------------------------------------------------------------------------
def test_reference_batch_equals_single_and_fsim(uw_image):
    x = uw_image.astype(np.float32)
    rng = np.random.default_rng(1)
    cands = np.stack(
        [np.clip(gaussian_filter(x, (s, s, 0)) + rng.normal(0, 4, x.shape), 0, 255) for s in (0.5, 1.0, 2.0)]
    ).astype(np.float32)
    ref32 = FSIMReference(uw_image)
    f_batch, fc_batch = ref32.score(cands)
    for k in range(3):
        f1, fc1 = ref32.score(cands[k])
        assert f1[0] == f_batch[k] and fc1[0] == fc_batch[k]
    exact = [fsim(uw_image, c) for c in cands]
    np.testing.assert_allclose(fc_batch, [e.fsimc for e in exact], rtol=0, atol=1e-6)
    np.testing.assert_allclose(f_batch, [e.fsim for e in exact], rtol=0, atol=1e-6)
    ref64 = FSIMReference(uw_image, dtype=np.float64)
    np.testing.assert_allclose(ref64.score(cands[:1])[1], [exact[0].fsimc], rtol=0, atol=1e-12)


def test_reference_odd_size_with_border_padding():
    # 775x801: F = round(775/256) = 3, front zero padding of the box filter, odd grids
    rng = np.random.default_rng(5)
    img = gaussian_filter(rng.uniform(0, 255, (775, 801, 3)), (2, 2, 0))
    dist = np.clip(img + rng.normal(0, 8, img.shape), 0, 255)
    want = fsim(img, dist)
    got = FSIMReference(img, dtype=np.float64).score(dist)
    assert got[0][0] == pytest.approx(want.fsim, abs=1e-12) and got[1][0] == pytest.approx(want.fsimc, abs=1e-12)


def test_reference_matches_matlab_value_in_float32(tid_pair):
    ref, dist = tid_pair
    f, fc = FSIMReference(ref).score(dist.astype(np.float32))
    assert abs(f[0] - 0.93674) <= 6e-6 and abs(fc[0] - 0.92587) <= 6e-6


def test_reference_grey_and_mask(tid_pair):
    ref, dist = tid_pair
    grey_r, grey_d = ref[..., 1], dist[..., 1]
    f, fc = FSIMReference(grey_r, dtype=np.float64).score(grey_d)
    assert f[0] == fc[0] == pytest.approx(fsim(grey_r, grey_d).fsim, abs=1e-12)
    full = np.ones(ref.shape[:2], bool)
    assert FSIMReference(ref, mask=full).score(dist)[1][0] == FSIMReference(ref).score(dist)[1][0]
    half = full.copy()
    half[:, ref.shape[1] // 2 :] = False
    assert FSIMReference(ref, mask=half).score(dist)[1][0] != FSIMReference(ref).score(dist)[1][0]


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------
GOOD = np.zeros((8, 9, 3), np.uint8)


@pytest.mark.parametrize(
    "a, b, exc, msg",
    [
        (GOOD, np.zeros((8, 10, 3), np.uint8), ValueError, "same shape"),
        (GOOD, GOOD[..., 0], ValueError, "same shape"),
        (GOOD.astype(np.int32), GOOD, TypeError, "dtype"),
        (GOOD.astype(bool), GOOD, TypeError, "dtype"),
        (GOOD, GOOD.tolist(), TypeError, "numpy array"),
        (np.zeros((0, 5), np.uint8), np.zeros((0, 5), np.uint8), ValueError, "empty"),
        (np.zeros((1, 1), np.uint8), np.zeros((1, 1), np.uint8), ValueError, "at least 2x2"),
        (np.zeros((1, 30, 3), np.uint8), np.zeros((1, 30, 3), np.uint8), ValueError, "at least 2x2"),
        (np.zeros((8, 9, 4), np.uint8), np.zeros((8, 9, 4), np.uint8), ValueError, "shape"),
        (GOOD, np.full((8, 9, 3), np.nan), ValueError, "NaN"),
        (GOOD, np.full((8, 9, 3), np.inf, np.float32), ValueError, "NaN or inf"),
        (GOOD, np.full((8, 9, 3), 256.0), ValueError, r"\[0, 255\]"),
        (GOOD, np.full((8, 9, 3), -1.0), ValueError, r"\[0, 255\]"),
    ],
)
def test_bad_input_raises_clear_errors(a, b, exc, msg):
    with pytest.raises(exc, match=msg):
        fsim(a, b)


def test_reference_bad_input():
    ref = FSIMReference(GOOD)
    with pytest.raises(ValueError, match="must have shape"):
        ref.score(np.zeros((2, 8, 10, 3), np.float32))
    with pytest.raises(ValueError, match="must have shape"):
        ref.score(np.zeros((8, 9), np.float32))  # grey candidate for a colour reference
    with pytest.raises(ValueError, match=r"candidates\[1\] contains NaN"):
        ref.score(np.stack([GOOD, np.full((8, 9, 3), np.nan)]))
    with pytest.raises(TypeError, match="numpy array"):
        ref.score(GOOD.tolist())
    with pytest.raises(TypeError, match="dtype"):
        FSIMReference(GOOD, dtype=np.float16)
    with pytest.raises(TypeError, match="boolean"):
        FSIMReference(GOOD, mask=np.ones((8, 9)))
    with pytest.raises(ValueError, match="no pixel"):
        FSIMReference(GOOD, mask=np.zeros((8, 9), bool))
