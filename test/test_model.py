"""UnderwaterModel: the base model unchanged, restore inverts degrade, the batched evaluator, Geometry."""
import os

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from uw_sil.sim import optics
from uw_sil.sim.camera import CameraModel
from uw_sil.sim.params import UnderwaterParams
from uw_sil.sim.render import Renderer
from uw_sil.sim.scene import facing_pose
from uw_sil.sim.model import Geometry, UnderwaterModel

P = UnderwaterParams(a=(0.3, 0.1, 0.08), b=(0.06, 0.3, 0.4), rho_f=0.05)


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(camera=CameraModel.from_fov(160, 120))
    yield r
    r.close()


@pytest.fixture(scope="module")
def frame(renderer):
    T = facing_pose(2.2, yaw=0.12, pitch=0.05)
    return T, renderer.render(T)


@pytest.mark.parametrize("fog", ["exp2", "exp", "none"])
def test_no_effects_equals_optics(frame, renderer, fog):
    T, rr = frame
    ours = UnderwaterModel(P, fog=fog).degrade(rr, renderer.camera)
    ref = optics.degrade(rr.rgb, rr.range, rr.depth, P.as_vector(), fog=fog)
    assert ours.dtype == np.float32 and ours.shape == ref.shape
    assert np.abs(ours - ref).max() <= 1e-6


@pytest.mark.parametrize("effects", [
    {},
    {"vignetting": "strong"},
    {"camera_response": "mild"},
    {"artificial_light": "strong"},
    {"artificial_light": "mild", "vignetting": "mild", "camera_response": "mild", "backscatter_coefficient": "strong"},
])
def test_restore_inverts_degrade(frame, renderer, effects):
    T, rr = frame
    cam = renderer.camera
    model = UnderwaterModel(P, effects)
    img = model.degrade(rr, cam, pose=T)
    res = model.restore(img, rr, cam, t0=0.1, max_gain=8.0, pose=T)
    obj = np.isfinite(rr.range)
    np.testing.assert_array_equal(res.restored_mask, obj)
    assert res.restored_fraction == pytest.approx(obj.mean())
    assert res.skipped == ()
    # where the caps do not bind (T_D >= t0, illumination >= 1/max_gain), the clean render comes back
    pm = model.prepare(rr, cam, pose=T)
    terms, _, _ = pm._terms(P.as_vector(), model.effect_vector(), seed=None, restoring=True)
    ok = obj & (terms.T_D.min(0) >= 0.1)
    if terms.illum is not None:
        ok &= terms.illum.min(0) >= 1 / 8.0
    assert ok.sum() > 0.9 * obj.sum()
    assert np.abs(res.image - rr.rgb)[ok].max() < 2e-5
    np.testing.assert_array_equal(res.image[~obj], np.clip(img[~obj], 0, 1))        # water stays as recorded


def test_restore_lists_what_it_cannot_undo(frame, renderer):
    T, rr = frame
    model = UnderwaterModel(P, "forward_scatter=mild,marine_snow=mild,sensor_noise=mild,vignetting=mild")
    img = model.degrade(rr, renderer.camera, rng=np.random.default_rng(0))
    res = model.restore((img * 255).round().astype(np.uint8), rr, renderer.camera)
    assert set(res.skipped) == {"forward_scatter", "marine_snow", "sensor_noise"}
    assert res.image.dtype == np.float32 and res.image.min() >= 0 and res.image.max() <= 1


def test_restore_b_override(frame, renderer):
    T, rr = frame
    model = UnderwaterModel(P)
    img = model.degrade(rr, renderer.camera)
    b2 = np.array([0.1, 0.25, 0.35])
    res = model.restore(img, rr, renderer.camera, b_override=b2)
    t = optics.transmission(rr.range, P.a) * optics.fog_factor(rr.depth, P.rho_f)[..., None]
    obj = np.isfinite(rr.range)
    expect = np.clip(b2 + (img - b2) / np.maximum(t, 0.1), 0, 1)
    np.testing.assert_allclose(res.image[obj], expect[obj], atol=1e-5)


def test_prepared_batch_matches_single(frame, renderer):
    T, rr = frame
    cam = renderer.camera
    model = UnderwaterModel(P, "artificial_light=mild,forward_scatter=mild,marine_snow=strong")
    pm = model.prepare(rr, cam, seed=7)
    assert pm.n_effect_params == len(pm.param_names) == len(pm.lower)
    rng = np.random.default_rng(0)
    base = np.tile(P.as_vector(), (3, 1))
    base[:, :3] *= rng.uniform(0.8, 1.2, (3, 3))
    ev = np.tile(model.effect_vector(), (3, 1))
    ev[1, pm.param_names.index("artificial_light.offset_x")] = -0.2
    out = pm(base, ev)
    assert out.shape == (3, 120, 160, 3) and out.dtype == np.float32
    for k in range(3):
        single = model.with_vectors(base[k], ev[k]).prepare(rr, cam, seed=7)(base[k], ev[k])
        np.testing.assert_array_equal(out[k], single)
    np.testing.assert_array_equal(pm(base, ev), out)                       # deterministic given the seed
    assert not np.array_equal(pm(base, ev, seed=8), out)                   # snow depends on the seed
    bad = ev.copy()
    bad[0, pm.param_names.index("forward_scatter.strength")] = 99.0
    with pytest.raises(ValueError, match="forward_scatter.strength"):
        pm(base, bad)
    with pytest.raises(ValueError, match="shape"):
        pm(base, ev[:, :-1])


def test_prepared_without_effects_matches_optics(frame, renderer):
    T, rr = frame
    pm = UnderwaterModel(P).prepare(rr, renderer.camera)
    base = np.stack([P.as_vector(), P.as_vector() * 1.1])
    ref = optics.PreparedRender(rr.rgb, rr.range, rr.depth)(base)
    np.testing.assert_array_equal(pm(base), ref)


def test_geometry_from_render(frame, renderer):
    T, rr = frame
    cam = renderer.camera
    g = Geometry.from_render(rr, cam)
    assert Geometry.from_render(rr, cam) is g                              # cached per render
    hit = np.isfinite(rr.range)
    np.testing.assert_array_equal(g.hit, hit)
    assert g.X.dtype == g.normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(g.X, axis=-1)[hit], rr.range[hit], rtol=1e-5)
    np.testing.assert_allclose(g.X[..., 2][hit], rr.depth[hit], rtol=1e-6)
    n = g.normals[(rr.labels == 1) & hit]
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-5)
    # the plate faces the camera: its normal is the panel's +z axis in the camera frame
    plate = np.median(n, axis=0)
    np.testing.assert_allclose(plate, T[:3, 2], atol=0.02)
    assert (g.normals[~hit] == 0).all()


def test_simcam_with_effects(frame):
    from uw_sil.sim.simcam import SimCamera

    T, rr = frame
    cam = CameraModel.from_fov(160, 120)
    with SimCamera(P, camera=cam, effects="vignetting=strong") as sim:
        img = sim.render(T).image
        ref = UnderwaterModel(P, {"vignetting": "strong"}).degrade(sim.renderer.render(T), cam)
        np.testing.assert_array_equal(img, ref)
        sim.set_effect_params({"vignetting.k1": -0.1})                    # live
        assert sim.effects["vignetting"]["k1"] == -0.1
        with pytest.raises(ValueError, match="not active"):
            sim.set_effect_params({"marine_snow.density": 10})
        with pytest.raises(ValueError, match="vignetting.k1"):
            sim.set_effect_params({"vignetting.k1": 9.0})
        assert sim.effects["vignetting"]["k1"] == -0.1                     # unchanged after a refused update
        sim.effects = None
        np.testing.assert_array_equal(sim.render(T).image, optics.degrade(rr.rgb, rr.range, rr.depth, P.as_vector()))


def test_restore_result_unpacks_to_three(frame, renderer):
    T, rr = frame
    img = UnderwaterModel(P).degrade(rr, renderer.camera)
    image, mask, fraction = UnderwaterModel(P, "forward_scatter=mild").restore(img, rr, renderer.camera)
    res = UnderwaterModel(P, "forward_scatter=mild").restore(img, rr, renderer.camera)
    assert res.skipped == ("forward_scatter",) and fraction == res.restored_fraction
