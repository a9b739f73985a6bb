"""SIL dehazing: the model's inverse (optics.PreparedInverse / UnderwaterModel.restore) behind enhance(), its
inputs, the per-frame background, the parameters file, PSNR/SSIM, and SIL against DCP/UDCP on a synthetic
frame whose clean radiance is known."""
import numpy as np
import pytest

from uw_sil.bags.synth import SensorNoise, add_sensor_noise
from uw_sil.enhance.sil import (Enhancer, enhance, estimate_background, frame_geometry, load_model_yaml,
                                load_params_yaml)
from uw_sil.metrics.fidelity import psnr, ssim
from uw_sil.sim.camera import CameraModel
from uw_sil.sim.model import UnderwaterModel
from uw_sil.sim.optics import PreparedInverse, degrade, restoration_gain, restore
from uw_sil.sim.params import UnderwaterParams
from uw_sil.sim.scene import facing_pose

CAM = CameraModel.from_fov(160, 120, 70.0)
P = UnderwaterParams(a=(0.42, 0.11, 0.08), b=(0.06, 0.32, 0.42), rho_f=0.08)


@pytest.fixture(scope="module")
def render():
    from uw_sil.sim.render import Renderer

    with Renderer(camera=CAM) as r:
        near = r.render(facing_pose(1.2))
        far = r.render(facing_pose(3.0, x=0.1, yaw=0.15))
    return near, far


def test_inverse_recovers_the_clean_image_to_float_precision(render):
    """Noise-free frames degraded by the model come back to the clean render wherever the geometry covers the
    panel (T > t0 there), and the water stays exactly as recorded: reference, fast path, and enhance()."""
    for rr in render:
        obj = rr.labels > 0
        assert obj.mean() > 0.05
        img = degrade(rr.rgb, rr.range, rr.depth, P.as_vector())
        ref = restore(img, rr.range, rr.depth, P.as_vector())
        fast = PreparedInverse().set_geometry(rr.range, rr.depth, obj)(img, P.as_vector())
        via_model = enhance(img, geometry=rr, model=UnderwaterModel(P), camera=CAM)
        via_depth = enhance(img, depth=rr.depth, mask=rr.labels, camera=CAM, model=P)   # range from the intrinsics
        for out in (ref, fast, via_model.image):
            assert np.abs(out - rr.rgb)[obj].max() < 2e-6
            np.testing.assert_array_equal(out[~obj], img[~obj])
        assert np.abs(via_depth.image - rr.rgb)[obj].max() < 1e-5
        assert via_model.restored_fraction == pytest.approx(obj.mean())
        np.testing.assert_array_equal(via_model.restored_mask, obj)


def test_inverse_undoes_effects_through_the_model_object(render):
    """With effects the same interface runs UnderwaterModel.restore, which inverts vignetting and the lamps
    to float precision wherever the degraded frame did not saturate."""
    rr = render[0]
    for effects in ({"vignetting": "strong"}, {"artificial_light": "mild"}):
        m = UnderwaterModel(P, effects)
        img = m.degrade(rr, CAM)
        res = enhance(img, geometry=rr, camera=CAM, model=m)
        np.testing.assert_allclose(res.image, m.restore(img, rr, CAM).image, atol=1e-7)
        ok = (rr.labels > 0) & (img.max(axis=2) < 1.0)
        assert ok.mean() > 0.1
        assert np.abs(res.image - rr.rgb)[ok].max() < 1e-5, effects
        assert res.skipped == ()


def test_uint8_frames_round_to_the_reference_and_keep_water_bit_exact(render):
    rr = render[1]
    obj = rr.labels > 0
    img = np.clip(np.rint(degrade(rr.rgb, rr.range, rr.depth, P.as_vector()) * 255), 0, 255).astype(np.uint8)
    out = enhance(img, geometry=rr, model=P).image
    assert out.dtype == np.uint8
    ref = restore(img / 255.0, rr.range, rr.depth, P.as_vector())
    assert np.abs(out / 255.0 - ref).max() <= 0.5 / 255 + 1e-6
    np.testing.assert_array_equal(out[~obj], img[~obj])


def test_gain_is_capped_at_one_over_t0_and_cached(render):
    rr = render[1]
    inv = PreparedInverse().set_geometry(rr.range, rr.depth)
    g = inv.gain(P.as_vector(), t0=0.3).copy()
    ref = restoration_gain(rr.range, rr.depth, P.as_vector(), t0=0.3)
    np.testing.assert_allclose(g, ref[inv.roi], rtol=2e-6)
    assert g.max() == pytest.approx(1 / 0.3, rel=1e-6)           # far red pixels hit the cap
    assert inv.gain(P.as_vector(), t0=0.3) is inv.gain(P.as_vector(), t0=0.3)
    with pytest.raises(ValueError, match="t0"):
        inv.gain(P.as_vector(), t0=0.0)
    # partial restoration beyond the cap: b + (I - b) / t0, not the clean radiance
    img = degrade(rr.rgb, rr.range, rr.depth, P.as_vector())
    out = inv(img, P.as_vector(), t0=0.3)
    capped = (ref[..., 0] > 3.33) & (rr.labels > 0)
    assert capped.any()
    expect = np.clip(P.b[0] + (img[..., 0] - P.b[0]) / 0.3, 0, 1)
    np.testing.assert_allclose(out[..., 0][capped], expect[capped], atol=1e-6)


def test_background_from_the_water(render):
    rr = render[1]
    rng = np.random.default_rng(3)
    clean = degrade(rr.rgb, rr.range, rr.depth, P.as_vector())
    noisy = add_sensor_noise(clean, SensorNoise(), rng)
    water = rr.labels == 0
    b = estimate_background(noisy, water)
    assert np.abs(b - np.array(P.b)).max() < 1.5 / 255
    drifted = UnderwaterParams(P.a, (0.1, 0.35, 0.45), P.rho_f)
    img = degrade(rr.rgb, rr.range, rr.depth, drifted.as_vector())
    fitted = enhance(img, geometry=rr, model=P)                          # the lamp/turbidity drifted after the fit
    fresh = enhance(img, geometry=rr, model=P, b_from_frame=True)
    obj = rr.labels > 0
    assert fresh.b_source == "frame" and np.allclose(fresh.background, drifted.b, atol=1e-6)
    assert np.abs(fresh.image - rr.rgb)[obj].mean() < 0.25 * np.abs(fitted.image - rr.rgb)[obj].mean()
    # a frame without water: the fitted b, and a warning
    full = rr.labels.copy()
    full[:] = 1
    depth = np.where(np.isfinite(rr.depth), rr.depth, 5.0).astype(np.float32)
    res = enhance(img, depth=depth, mask=full, camera=CAM, model=P, b_from_frame=True)
    assert res.b_source == "fit (no water)" and np.allclose(res.background, P.b)
    assert res.warnings and "water" in res.warnings[0]


@pytest.mark.parametrize("change,message", [
    (lambda d, m: d.__setitem__((0, 0), np.nan), "NaN"),
    (lambda d, m: d.__setitem__((5, 5), 0.0), "<= 0"),
    (lambda d, m: d.__setitem__((5, 5), -np.inf), "<= 0"),
    (lambda d, m: m.__setitem__((0, 0), 1), "object where the sim depth is inf"),
])
def test_bad_sim_geometry_is_refused_clearly(render, change, message):
    rr = render[1]
    d, m = rr.depth.copy(), rr.labels.copy()
    assert np.isinf(d[0, 0]) and m[0, 0] == 0
    change(d, m)
    img = np.zeros((120, 160, 3), np.uint8)
    with pytest.raises(ValueError, match=message):
        enhance(img, depth=d, mask=m, camera=CAM, model=P)


def test_bad_images_and_sizes_are_refused_clearly(render):
    rr = render[1]
    with pytest.raises(ValueError, match="grey"):
        enhance(np.zeros((120, 160), np.uint8), geometry=rr, model=P)
    with pytest.raises(ValueError, match="grey"):
        enhance(np.zeros((120, 160), np.uint8), "dcp")
    with pytest.raises(ValueError, match=r"160x120 but the image is 80x60"):
        enhance(np.zeros((60, 80, 3), np.uint8), geometry=rr, model=P)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        enhance(np.full((120, 160, 3), 2.0), geometry=rr, model=P)
    with pytest.raises(ValueError, match="model"):
        enhance(np.zeros((120, 160, 3), np.uint8), geometry=rr)
    with pytest.raises(ValueError, match="unknown method"):
        enhance(np.zeros((120, 160, 3), np.uint8), "clahe")
    with pytest.raises(ValueError, match="camera"):
        frame_geometry(depth=rr.depth, mask=rr.labels)


def test_sil_beats_dcp_and_udcp_against_the_truth(render):
    """On a noisy synthetic frame (clean radiance known) SIL is closer to the truth than DCP and UDCP."""
    rng = np.random.default_rng(0)
    for rr in render:
        obj = rr.labels > 0
        img = add_sensor_noise(degrade(rr.rgb, rr.range, rr.depth, P.as_vector()), SensorNoise(), rng)
        e = Enhancer(P)
        scores = {m: (psnr(e.enhance(img, m, geometry=rr).image, rr.rgb, obj),
                      ssim(e.enhance(img, m, geometry=rr).image, rr.rgb, obj)) for m in ("sil", "dcp", "udcp")}
        for m in ("dcp", "udcp"):
            assert scores["sil"][0] > scores[m][0] + 10, scores
            assert scores["sil"][1] > scores[m][1] + 0.05, scores


def test_psnr_and_ssim():
    rng = np.random.default_rng(1)
    a = rng.random((40, 50, 3))
    assert psnr(a, a) == np.inf and ssim(a, a) == pytest.approx(1.0)
    b = np.clip(a + 0.1, 0, 1)
    mse = np.mean((a - b) ** 2)
    assert psnr(b, a) == pytest.approx(10 * np.log10(1 / mse))
    mask = np.zeros((40, 50), bool)
    mask[10:20, 10:30] = True
    assert psnr(b, a, mask) == pytest.approx(10 * np.log10(1 / np.mean((a - b)[mask] ** 2)))
    noisy = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    noisier = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    assert 1 > ssim(noisy, a) > ssim(noisier, a) > 0
    u8 = np.rint(a * 255).astype(np.uint8)
    assert psnr(u8, a) > 50
    with pytest.raises(ValueError, match="no pixel"):
        psnr(a, a, np.zeros((40, 50)))
    with pytest.raises(ValueError, match="shape"):
        ssim(a, a[:10])


def test_params_file(tmp_path):
    good = tmp_path / "fit.yaml"
    good.write_text("/**:\n  ros__parameters:\n    a_r: 0.4\n    a_g: 0.1\n    a_b: 0.08\n    b_r: 0.05\n"
                    "    b_g: 0.3\n    b_b: 0.4\n    rho_f: 0.05\n    fog_mode: exp\n    noise_sigma: 1.2\n")
    params, fog, ros = load_params_yaml(good)
    assert params == UnderwaterParams((0.4, 0.1, 0.08), (0.05, 0.3, 0.4), 0.05) and fog == "exp"
    assert ros["noise_sigma"] == 1.2
    model = load_model_yaml(good)
    assert model.params == params and model.fog == "exp" and not model.effects
    with_effects = tmp_path / "fx.yaml"
    with_effects.write_text(good.read_text() + "    vignetting.k1: -0.2\n")
    assert "vignetting" in load_model_yaml(with_effects).effects
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_params_yaml(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    for text, message in (("a: [1, 2", "not valid YAML"), ("- 1\n- 2\n", "must map"),
                          ("/**:\n  ros__parameters:\n    a_r: 0.4\n", "lacks a_g"),
                          (good.read_text().replace("b_b: 0.4", "b_b: 1.4"), "b_b"),
                          (good.read_text().replace("fog_mode: exp", "fog_mode: thick"), "fog_mode"),
                          ("/**:\n  something: 1\n", "no ros__parameters")):
        bad.write_text(text)
        with pytest.raises(ValueError, match=message):
            load_model_yaml(bad)
