"""Eq. 1 and fog against hand-computed pixels; no-hit pixels; batching; validation."""
import math

import numpy as np
import pytest

from uw_sil.sim.optics import PreparedRender, degrade, fog_factor, transmission


def _scene():
    rgb = np.array([[[0.8, 0.5, 0.2], [0.1, 0.9, 0.4]],
                    [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], dtype=np.float32)
    rng = np.array([[2.0, 3.5], [np.inf, 1.0]], dtype=np.float32)
    depth = np.array([[1.9, 3.0], [np.inf, 0.8]], dtype=np.float32)
    return rgb, rng, depth


def test_eq1_without_fog_matches_hand_computation():
    rgb, rng, depth = _scene()
    p = [0.4, 0.2, 0.1, 0.05, 0.3, 0.45, 0.0]
    out = degrade(rgb, rng, depth, p, fog="exp2")
    # pixel (0, 0), red: i = 0.8, r = 2, a = 0.4, b = 0.05
    e = math.exp(-2.0 * 0.4)
    assert out[0, 0, 0] == pytest.approx(0.8 * e + (1 - e) * 0.05, abs=1e-6)
    # pixel (0, 1), blue: i = 0.4, r = 3.5, a = 0.1, b = 0.45
    e = math.exp(-3.5 * 0.1)
    assert out[0, 1, 2] == pytest.approx(0.4 * e + (1 - e) * 0.45, abs=1e-6)


def test_eq1_with_exp2_fog_matches_hand_computation():
    rgb, rng, depth = _scene()
    p = [0.4, 0.2, 0.1, 0.05, 0.3, 0.45, 0.3]
    out = degrade(rgb, rng, depth, p, fog="exp2")
    # pixel (1, 1), green: i = 1, r = 1, z = 0.8, a = 0.2, b = 0.3
    e = math.exp(-1.0 * 0.2)
    f = math.exp(-(0.3 * 0.8) ** 2)
    expected = e * (f * 1.0 + (1 - f) * 0.3) + (1 - e) * 0.3
    assert out[1, 1, 1] == pytest.approx(expected, abs=1e-6)
    # exp fog
    out = degrade(rgb, rng, depth, p, fog="exp")
    f = math.exp(-0.3 * 0.8)
    assert out[1, 1, 1] == pytest.approx(e * (f + (1 - f) * 0.3) + (1 - e) * 0.3, abs=1e-6)
    # fog changes the image: it acts
    assert not np.allclose(degrade(rgb, rng, depth, p), degrade(rgb, rng, depth, p[:6] + [0.0]))


def test_no_hit_pixels_are_background_even_with_zero_attenuation():
    rgb, rng, depth = _scene()
    p = [0.0, 0.0, 0.0, 0.11, 0.22, 0.33, 0.0]
    out = degrade(rgb, rng, depth, p)
    np.testing.assert_allclose(out[1, 0], [0.11, 0.22, 0.33], atol=1e-7)
    assert np.isfinite(out).all()
    # zero attenuation, no fog: hit pixels are the clean image
    np.testing.assert_allclose(out[0, 0], rgb[0, 0], atol=1e-7)


def test_far_range_tends_to_background():
    rgb = np.full((1, 1, 3), 0.9, np.float32)
    out = degrade(rgb, np.array([[1e4]]), np.array([[1e4]]), [0.3, 0.3, 0.3, 0.1, 0.2, 0.3, 0.0])
    np.testing.assert_allclose(out[0, 0], [0.1, 0.2, 0.3], atol=1e-6)


def test_batch_equals_one_at_a_time():
    rng_ = np.random.default_rng(0)
    rgb = rng_.random((12, 16, 3), dtype=np.float32)
    r = rng_.uniform(0.5, 4, (12, 16)).astype(np.float32)
    r[:, :3] = np.inf
    z = r * 0.9
    ps = np.column_stack([rng_.uniform(0, 0.6, (5, 3)), rng_.uniform(0, 1, (5, 3)), rng_.uniform(0, 0.4, 5)])
    prep = PreparedRender(rgb, r, z)
    batch = prep(ps)
    assert batch.shape == (5, 12, 16, 3) and batch.dtype == np.float32
    for k in range(5):
        np.testing.assert_allclose(batch[k], degrade(rgb, r, z, ps[k]), atol=1e-7)
    buf = np.empty_like(batch)
    assert prep(ps, out=buf) is buf
    np.testing.assert_array_equal(buf, batch)
    one = np.empty_like(batch[0])
    prep(ps[2], out=one)
    np.testing.assert_array_equal(one, batch[2])


def test_transmission_and_fog_helpers():
    e = transmission(np.array([0.0, 2.0, np.inf]), [0.5, 0.0, 1.0])
    np.testing.assert_allclose(e[1], [math.exp(-1.0), 1.0, math.exp(-2.0)], rtol=1e-6)
    np.testing.assert_array_equal(e[2], [0, 0, 0])
    f = fog_factor(np.array([0.0, 2.0, np.inf]), 0.5)
    np.testing.assert_allclose(f, [1.0, math.exp(-1.0), 0.0], rtol=1e-6)
    with pytest.raises(ValueError, match="fog mode"):
        fog_factor(np.ones(2), 0.1, mode="linear")


@pytest.mark.parametrize("bad, match", [
    ([0.1] * 6, "length 7"),
    ([-0.1, 0, 0, 0.1, 0.1, 0.1, 0], "a_r"),
    ([0.1, 0.1, 0.1, 1.5, 0.1, 0.1, 0], "b_r"),
    ([0.1, 0.1, 0.1, 0.1, 0.1, 0.1, np.nan], "rho_f"),
])
def test_parameter_validation(bad, match):
    rgb, rng, depth = _scene()
    with pytest.raises(ValueError, match=match):
        degrade(rgb, rng, depth, bad)


def test_render_validation():
    rgb, rng, depth = _scene()
    with pytest.raises(ValueError, match="range shape"):
        degrade(rgb, rng[:1], depth, [0.1] * 7)
    with pytest.raises(TypeError, match="float"):
        degrade((rgb * 255).astype(np.uint8), rng, depth, [0.1] * 7)
    with pytest.raises(ValueError, match="NaN"):
        degrade(rgb, np.full((2, 2), np.nan), depth, [0.1] * 7)


def test_prepared_planar_equals_the_batched_call_and_cover_is_the_block_average():
    """planar() computes only the hit pixels; water pixels are b exactly, as in the full-plane arithmetic."""
    rng = np.random.default_rng(3)
    h, w = 24, 32
    rgb = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    r = rng.uniform(1, 4, (h, w)).astype(np.float32)
    z = (r * 0.9).astype(np.float32)
    r[:, :10] = np.inf
    z[:, :10] = np.inf
    params = np.array([[0.4, 0.1, 0.08, 0.06, 0.32, 0.42, 0.08], [0.2, 0.3, 0.5, 0.5, 0.1, 0.9, 0.0]])
    for fog in ("exp2", "exp", "none"):
        prep = PreparedRender(rgb, r, z, fog=fog)
        batch = prep(params)
        for k, p in enumerate(params):
            planes = prep.planar(p, work=prep.work_buffers())
            assert np.array_equal(np.moveaxis(planes.reshape(3, h, w), 0, -1), batch[k])
            assert np.all(planes.reshape(3, h, w)[:, :, :10] == p[3:6].astype(np.float32)[:, None, None])
    # a block half on the model at constant range: the average of its full-resolution pixels
    cover = np.full((h, w), 0.5, np.float32)
    rr = np.full((h, w), 2.0, np.float32)
    half = PreparedRender(rgb, rr, rr, cover=cover)(params[0])
    full = PreparedRender(rgb, rr, rr)(params[0])
    np.testing.assert_allclose(half, (full + params[0][3:6]) / 2, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="cover"):
        PreparedRender(rgb, rr, rr, cover=cover * 3)
