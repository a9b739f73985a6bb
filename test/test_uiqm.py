"""UIQM / UCIQE: hand-computed sub-measures on tiny images, grey images, and haze lowering both."""
import math

import cv2
import numpy as np
import pytest

from uw_sil.metrics.uiqm import (PLIP_GAMMA, PLIP_K, eme, uciqe, uciqe_terms, uicm, uiconm, uiqm,
                                 uism)


def _texture(seed=0, shape=(240, 320)):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((*shape, 3)).astype(np.float32), (0, 0), 2)
    return (img - img.min()) / (img.max() - img.min())


def _haze(img, t, A):
    return (img * t + np.asarray(A, np.float32) * (1 - t)).astype(np.float32)


@pytest.mark.parametrize("A", [(0.1, 0.55, 0.65), (0.5, 0.5, 0.5)], ids=["blue-green", "grey"])
def test_haze_lowers_both_measures(A):
    img = _texture()
    hazy = _haze(img, 0.5, A)
    assert uiqm(hazy) < uiqm(img)
    assert uciqe(hazy) < uciqe(img)
    assert uicm(hazy) < uicm(img)
    assert uiconm(hazy) < uiconm(img)
    assert uism(hazy) < uism(img)
    t0, t1 = uciqe_terms(img), uciqe_terms(hazy)
    assert t1["sigma_c"] < t0["sigma_c"] and t1["con_l"] < t0["con_l"]
    # more haze, lower still
    assert uiqm(_haze(img, 0.25, A)) < uiqm(hazy)
    assert uciqe(_haze(img, 0.25, A)) < uciqe(hazy)


def test_constant_grey_image_scores_zero():
    grey = np.full((64, 64, 3), 0.5, np.float32)
    assert uicm(grey) == 0.0
    assert uism(grey) == 0.0
    assert uiconm(grey) == 0.0
    assert uiqm(grey) == 0.0
    assert uciqe(grey) == pytest.approx(0.0, abs=1e-3)


def _srgb_lightness(v):
    """CIE L* (0-100) of the sRGB grey v in [0, 1], from the standard formulas (not from OpenCV)."""
    lin = v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4
    f = lin ** (1 / 3) if lin > (6 / 29) ** 3 else lin / (3 * (6 / 29) ** 2) + 4 / 29
    return 116 * f - 16


def test_grey_ramp_uciqe_is_luminance_contrast_only():
    v = np.arange(101) / 100.0                         # 101 pixels: the 1st and 99th percentiles are samples 1 and 99
    ramp = np.repeat(v[None, :, None], 3, axis=2).astype(np.float32)
    terms = uciqe_terms(ramp)
    assert terms["sigma_c"] == pytest.approx(0.0, abs=1e-3)
    assert terms["mu_s"] == pytest.approx(0.0, abs=1e-3)
    expected = (_srgb_lightness(0.99) - _srgb_lightness(0.01)) / 100
    assert terms["con_l"] == pytest.approx(expected, abs=2e-3)
    assert uciqe(ramp) == pytest.approx(0.2745 * expected, abs=2e-3)
    assert uicm(ramp) == 0.0                           # no opponent colour at all


def test_uciqe_of_pure_red_is_its_saturation():
    red = np.zeros((8, 8, 3), np.uint8)
    red[..., 0] = 255
    # sRGB red is L* 53.24, a* 80.09, b* 67.20 (D65): chroma 104.55, saturation C/L = 1.9638
    terms = uciqe_terms(red)
    assert terms["sigma_c"] == pytest.approx(0.0, abs=1e-6) and terms["con_l"] == pytest.approx(0.0, abs=1e-6)
    assert terms["mu_s"] == pytest.approx(math.hypot(80.09, 67.20) / 53.24, abs=2e-3)
    assert uciqe(red) == pytest.approx(0.2576 * math.hypot(80.09, 67.20) / 53.24, abs=1e-3)


def test_uicm_by_hand():
    # 10 pixels (K = 10): trimming drops ceil(0.1 K) = 1 smallest and floor(0.1 K) = 1 largest value
    img = np.zeros((2, 5, 3), np.uint8)
    img[..., 0] = np.arange(0, 100, 10).reshape(2, 5)   # R = 0, 10, ..., 90; G = B = 0
    mu_rg, var_rg = 45.0, 825.0                        # mean(10..80); mean((r - 45)^2)
    mu_yb, var_yb = 22.5, 825.0 / 4                    # YB = R / 2
    expected = -0.0268 * math.hypot(mu_rg, mu_yb) + 0.1586 * math.sqrt(var_rg + var_yb)
    assert uicm(img) == pytest.approx(expected, rel=1e-12)
    # alpha * K = 0.1 * 30 is 3.0000000000000004 in floating point: still 3 values trimmed each side
    img30 = np.zeros((3, 10, 3), np.uint8)
    img30[..., 0] = np.arange(30).reshape(3, 10) * 5
    r = np.arange(30) * 5.0
    mu = r[3:27].mean()
    expected30 = (-0.0268 * math.hypot(mu, mu / 2)
                  + 0.1586 * math.sqrt(np.mean((r - mu) ** 2) + np.mean((r / 2 - mu / 2) ** 2)))
    assert uicm(img30) == pytest.approx(expected30, rel=1e-12)


def test_eme_by_hand():
    block = np.full((8, 8), 10.0)
    block[0, 0], block[7, 7] = 2.0, 50.0
    assert eme(block) == pytest.approx(2 * math.log(25))
    two = np.hstack([block, np.pad(np.ones((7, 8)), ((1, 0), (0, 0)))])  # 2nd block has a 0: contributes 0
    assert eme(two) == pytest.approx(2 / 2 * math.log(25))
    # the remainder beyond whole blocks is ignored
    assert eme(np.pad(block, ((0, 5), (0, 7)), constant_values=1000.0)) == pytest.approx(2 * math.log(25))


def test_uiconm_by_hand_with_plip():
    def q(hi, lo):
        sub = PLIP_K * (hi - lo) / (PLIP_K - lo)
        add = hi + lo - hi * lo / PLIP_GAMMA
        return sub / add

    one = np.full((8, 8, 3), 10, np.uint8)
    one[3, 3] = 30
    # one block: 1 (x) S = S, so UIConM = -q ln q
    q1 = q(30.0, 10.0)
    assert uiconm(one) == pytest.approx(-q1 * math.log(q1), rel=1e-9)
    second = np.full((8, 8, 3), 50, np.uint8)
    second[0, 0] = 200
    two = np.hstack([one, second])
    q2 = q(200.0, 50.0)
    S = q1 * math.log(q1) + q2 * math.log(q2)
    expected = -(PLIP_GAMMA - PLIP_GAMMA * (1 - S / PLIP_GAMMA) ** 0.5)   # (1/2) (x) S
    assert uiconm(two) == pytest.approx(expected, rel=1e-9)


def test_uism_weights_channels_by_luma():
    tex = _texture(1, (64, 64))[..., 0].astype(np.float64)
    grey = np.repeat(tex[..., None], 3, axis=2)
    edge = np.hypot(cv2.Sobel(tex * 255, cv2.CV_64F, 1, 0), cv2.Sobel(tex * 255, cv2.CV_64F, 0, 1)) * tex * 255
    assert uism(grey) == pytest.approx(eme(edge), rel=1e-9)          # 0.299 + 0.587 + 0.114 = 1
    only_green = np.full_like(grey, 0.5)
    only_green[..., 1] = tex
    assert uism(only_green) == pytest.approx(0.587 * eme(edge), rel=1e-9)


def test_uint8_and_float_inputs_agree():
    u8 = np.rint(_texture(2, (64, 96)) * 255).astype(np.uint8)
    f = u8.astype(np.float64) / 255
    assert uiqm(u8) == pytest.approx(uiqm(f), rel=1e-9)
    assert uciqe(u8) == pytest.approx(uciqe(f), rel=1e-5)


@pytest.mark.parametrize("fn", [uiqm, uciqe, uicm, uism, uiconm])
@pytest.mark.parametrize("image, match", [
    (np.zeros((16, 16)), r"\(H, W, 3\)"),
    (np.zeros((16, 16, 3), np.int32), "dtype"),
    (np.full((16, 16, 3), 2.0), r"\[0, 1\]"),
    (np.full((16, 16, 3), np.inf), "NaN or infinite"),
])
def test_bad_images_are_refused(fn, image, match):
    with pytest.raises(ValueError, match=match):
        fn(image)


def test_image_smaller_than_a_block_is_refused():
    with pytest.raises(ValueError, match="block"):
        uiqm(np.zeros((4, 16, 3), np.uint8))
