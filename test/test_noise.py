"""Noise estimation on real-like frames and the fixed noise field added to simulated candidates."""
import numpy as np
import pytest

from uw_sil.sim.noise import NoiseField, estimate_noise_sigma


def test_estimate_recovers_known_sigma_despite_edges():
    rng = np.random.default_rng(0)
    img = np.full((120, 160, 3), 90.0)
    img[:, 80:] = 170.0                     # a strong edge
    img[40:60, :, 1] += 40.0                # and a stripe in one channel
    sigma = np.array([1.5, 3.0, 5.0])
    noisy = img + rng.normal(0, 1, img.shape) * sigma
    est = estimate_noise_sigma(noisy)
    np.testing.assert_allclose(est, sigma, rtol=0.08)


def test_estimate_uses_only_masked_pixels():
    rng = np.random.default_rng(1)
    img = rng.normal(100, 2.0, (60, 80, 3))
    img[:, 40:] = rng.normal(100, 20.0, (60, 40, 3))
    mask = np.zeros((60, 80), bool)
    mask[:, :40] = True
    np.testing.assert_allclose(estimate_noise_sigma(img, mask), 2.0, rtol=0.1)
    assert np.all(estimate_noise_sigma(img) > 3.0)
    with pytest.raises(ValueError, match="pixel pairs"):
        estimate_noise_sigma(img, np.zeros((60, 80), bool))


@pytest.mark.parametrize("sigma", [0.3, 0.6, 0.8, 1.0, 1.3, 2.0])
def test_estimate_of_rounded_noise_is_the_noise_before_rounding(sigma):
    """An 8-bit recording's noise of about a grey level: the median of integer differences is an integer, so
    the plain MAD read 0, 1.05 or 2.1 grey levels (0.6 -> 1.05, 1.3 -> 1.05, 0.3 -> 0). The estimate is the noise
    a simulation must add before it rounds, with edges and a slope in the frame."""
    rng = np.random.default_rng(int(sigma * 10))
    img = np.linspace(3.0, 30.0, 320)[None, :, None] + np.zeros((240, 1, 3))
    img[:, 200:] += 60.0                                     # an edge
    noisy = np.clip(np.rint(img + rng.normal(0, sigma, img.shape)), 0, 255).astype(np.uint8)
    np.testing.assert_allclose(estimate_noise_sigma(noisy), sigma, rtol=0.05)
    np.testing.assert_allclose(estimate_noise_sigma(noisy.astype(np.float32)), sigma, rtol=0.05)


def test_quantized_noise_free_image_has_zero_sigma():
    img = np.full((50, 50, 3), 77, np.uint8)
    np.testing.assert_array_equal(estimate_noise_sigma(img), 0.0)


def test_noise_field_is_fixed_and_has_the_sigma():
    f1 = NoiseField((100, 100, 3), [1.0, 2.0, 4.0], seed=3)
    f2 = NoiseField((100, 100, 3), [1.0, 2.0, 4.0], seed=3)
    np.testing.assert_array_equal(f1.field, f2.field)
    np.testing.assert_allclose(f1.field.reshape(-1, 3).std(axis=0), [1, 2, 4], rtol=0.05)
    imgs = np.full((2, 100, 100, 3), 128.0, np.float32)
    out = f1.apply(imgs)
    assert out is imgs
    np.testing.assert_array_equal(out[0], out[1])                       # same realization for every candidate
    np.testing.assert_array_equal(out[0], np.clip(np.rint(128.0 + f1.field), 0, 255))
    with pytest.raises(ValueError, match="sigma"):
        NoiseField((4, 4, 3), -1.0)
