"""Dark channel prior (He et al.) and UDCP (Drews et al.) on synthetic hazy images with known t and A."""
import numpy as np
import pytest
from scipy.ndimage import minimum_filter

from uw_sil.enhance.dcp import DehazeResult, dehaze_dcp

H, W, WATER_ROWS = 240, 320, 40


def _clean(seed=0):
    """A colourful texture of 4x4-pixel cells; in every cell one random channel is nearly black, so
    every 15x15 patch holds dark pixels in each channel (the dark channel prior holds: J_dark ~ 0.02)."""
    rng = np.random.default_rng(seed)
    cells = rng.uniform(0.25, 1.0, (H // 4, W // 4, 3))
    dark = rng.integers(0, 3, (H // 4, W // 4))
    np.put_along_axis(cells, dark[..., None], 0.02, axis=2)
    return np.repeat(np.repeat(cells, 4, axis=0), 4, axis=1)


def _transmission():
    """Depth grows to the right: t from 0.8 down to 0.3; the top rows are open water (t = 0)."""
    t = np.broadcast_to(np.linspace(0.8, 0.3, W), (H, W)).copy()
    t[:WATER_ROWS] = 0.0
    return t


def _haze(J, t, A):
    # He et al.'s haze imaging model
    return (J * t[..., None] + np.asarray(A) * (1.0 - t[..., None])).astype(np.float32)


def _dark(img, channels=(0, 1, 2), patch=15):
    return minimum_filter(img[..., list(channels)].min(axis=2), size=patch, mode="nearest")


SCENE = (slice(WATER_ROWS + 30, H - 10), slice(20, W - 20))  # away from the water edge and the border
A_TRUE = np.array([0.75, 0.85, 0.9])


def test_dark_channel_goes_to_zero_and_airlight_is_recovered():
    J, t = _clean(), _transmission()
    I = _haze(J, t, A_TRUE)
    res = dehaze_dcp(I)
    assert isinstance(res, DehazeResult)
    np.testing.assert_allclose(res.atmospheric_light, A_TRUE, atol=0.01)
    dark_in, dark_out = _dark(I)[SCENE].mean(), _dark(res.image)[SCENE].mean()
    assert dark_in > 0.2
    assert dark_out < 0.2 * dark_in
    # the refined transmission follows the true one (omega = 0.95 keeps ~5 % haze: t_est >= t_true)
    err = res.transmission[SCENE] - t[SCENE]
    assert np.abs(err).mean() < 0.06
    assert res.transmission.shape == (H, W) and res.transmission.dtype == np.float32


def test_recovers_scene_radiance():
    J, t = _clean(), _transmission()
    I = _haze(J, t, A_TRUE)
    input_err = np.abs(I[SCENE] - J[SCENE]).mean()
    assert input_err > 0.15
    # without omega's haze and without refinement the inversion is near exact (transmission and recovery
    # of He et al. with omega = 1: CVPR 2009 Eq. 12 (or 11) and Eq. 16, see uw_sil/enhance/dcp.py)
    exact = dehaze_dcp(I, omega=1.0, guided_radius=0)
    assert np.abs(exact.image[SCENE] - J[SCENE]).mean() < 0.02
    # He et al.'s settings: omega 0.95 leaves a little haze, the guided filter smooths t
    default = dehaze_dcp(I)
    assert np.abs(default.image[SCENE] - J[SCENE]).mean() < 0.25 * input_err


def test_airlight_is_brightest_input_among_top_dark_channel_pixels():
    img = np.full((100, 100, 3), 0.2, np.float32)        # 10,000 pixels: the top 0.1 % are 10 pixels
    ys, xs = np.unravel_index(np.arange(10) * 37 + 2000, (100, 100))
    img[ys, xs] = (0.9, 0.95, 0.92)                      # dark channel 0.9: the candidates
    img[ys[3], xs[3]] = (0.9, 1.0, 1.0)                  # the brightest candidate
    img[5, 5] = (1.0, 1.0, 0.1)                          # brighter, but its dark channel is low
    res = dehaze_dcp(img, patch=1, guided_radius=0)
    np.testing.assert_allclose(res.atmospheric_light, (0.9, 1.0, 1.0), atol=1e-6)
    # ties at the highest intensity are averaged
    img[ys[4], xs[4]] = (0.96, 0.98, 0.96)               # same mean intensity as (0.9, 1, 1)
    res = dehaze_dcp(img, patch=1, guided_radius=0)
    np.testing.assert_allclose(res.atmospheric_light, (0.93, 0.99, 0.98), atol=1e-6)


def _blue_green(red_seed):
    """Underwater frame: G and B follow the haze model, red is absorbed (weak noise, no information)."""
    J, t = _clean(), _transmission()
    I = _haze(J, t, (0.0, 0.55, 0.65))
    I[..., 0] = np.random.default_rng(red_seed).uniform(0.0, 0.02, (H, W))
    return I, J, t


def test_udcp_sees_blue_green_haze_that_dcp_misses():
    I, J, t = _blue_green(red_seed=1)
    dcp, udcp = dehaze_dcp(I, variant="dcp"), dehaze_dcp(I, variant="udcp")
    # UDCP finds the veiling light in the water and the transmission of the scene
    np.testing.assert_allclose(udcp.atmospheric_light[1:], (0.55, 0.65), atol=0.01)
    assert np.abs(udcp.transmission[SCENE] - t[SCENE]).mean() < 0.06
    # DCP's dark channel is the absorbed red channel: it sees (almost) no haze
    assert dcp.transmission[SCENE].mean() > 0.9 > t[SCENE].mean() + 0.3
    # so UDCP restores G and B, DCP leaves them near the hazy input
    gb = (*SCENE, slice(1, 3))
    err_in = np.abs(I[gb] - J[gb]).mean()
    assert np.abs(udcp.image[gb] - J[gb]).mean() < 0.3 * err_in
    assert np.abs(dcp.image[gb] - J[gb]).mean() > 0.7 * err_in
    # UDCP's estimate ignores the red channel: other red noise, same raw transmission (the guided
    # filter's grey guide does see red, so only the unrefined t is exactly the same)
    raw = [dehaze_dcp(_blue_green(seed)[0], variant="udcp", guided_radius=0) for seed in (1, 2)]
    np.testing.assert_array_equal(raw[0].transmission, raw[1].transmission)
    np.testing.assert_array_equal(raw[0].atmospheric_light[1:], raw[1].atmospheric_light[1:])


def test_dtype_round_trip_and_determinism():
    I = _haze(_clean(), _transmission(), A_TRUE)
    u8 = np.rint(I * 255).astype(np.uint8)
    out8 = dehaze_dcp(u8)
    assert out8.image.dtype == np.uint8 and out8.image.shape == u8.shape
    outf = dehaze_dcp(u8.astype(np.float32) / 255)
    assert outf.image.dtype == np.float32
    assert np.abs(out8.image.astype(int) - np.rint(outf.image * 255).astype(int)).max() <= 1
    out64 = dehaze_dcp(u8.astype(np.float64) / 255, variant="udcp")
    assert out64.image.dtype == np.float64
    assert 0.0 <= out64.image.min() and out64.image.max() <= 1.0
    again = dehaze_dcp(u8)
    np.testing.assert_array_equal(again.image, out8.image)
    np.testing.assert_array_equal(again.atmospheric_light, out8.atmospheric_light)


@pytest.mark.parametrize("image, match", [
    (np.zeros((20, 20)), r"\(H, W, 3\)"),
    (np.zeros((20, 20, 4)), r"\(H, W, 3\)"),
    (np.zeros((0, 20, 3)), "empty"),
    (np.zeros((20, 20, 3), np.int16), "dtype"),
    (np.full((20, 20, 3), 1.5), r"\[0, 1\]"),
    (np.full((20, 20, 3), np.nan), "NaN"),
])
def test_bad_images_are_refused(image, match):
    with pytest.raises(ValueError, match=match):
        dehaze_dcp(image)


@pytest.mark.parametrize("kw, match", [
    ({"variant": "red"}, "variant"),
    ({"patch": 14}, "odd"),
    ({"patch": 0}, "odd"),
    ({"omega": 0.0}, "omega"),
    ({"t0": 0.0}, "t0"),
    ({"guided_radius": -1}, "guided_radius"),
    ({"guided_eps": 0.0}, "guided_eps"),
])
def test_bad_parameters_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        dehaze_dcp(np.zeros((20, 20, 3), np.float32), **kw)
