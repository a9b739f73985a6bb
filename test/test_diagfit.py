"""The diagnosis's fits on reduced frames (uw_sil.fit.diagfit, uw_sil.fit.residuals): the least-squares fits
are not pulled by a few wrong pixels, and a reduced frame's lamp shading is the block mean of the
full-resolution one."""
import os

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from uw_sil.fit.diagfit import ROBUST_SCALE, EffectModel, ls_fit, residual_energy, robust_energy
from uw_sil.fit.residuals import DiagFrame, box_down, reduce_frame


class _Ramp:
    """A toy model for ls_fit: the image is ``offset + gain * ramp`` (grey levels / 255), one frame."""

    def __init__(self, image, ramp):
        self.rframes = [type("RF", (), {"image": image})()]
        self.ramp = ramp

    def bounds(self):
        return np.array([0.0, 0.0]), np.array([1.0, 1.0])

    def simulate(self, k, X):
        X = np.atleast_2d(X)
        return X[:, 0, None, None, None] + X[:, 1, None, None, None] * self.ramp[None]


def test_least_squares_is_not_pulled_by_a_few_wrong_pixels():
    # 2 % of the pixels 60 grey levels off (the sides of small parts at 1/8 of the resolution, specks): plain
    # least squares moves the offset by 1.2 grey levels towards them; the robust fit stays within 0.1
    rng = np.random.default_rng(0)
    ramp = np.repeat(np.linspace(0, 1, 50, dtype=np.float32)[None, :, None], 40, axis=0).repeat(3, axis=2)
    truth = np.array([40 / 255, 100 / 255])
    image = (truth[0] + truth[1] * ramp) * 255 + rng.normal(0, 0.3, ramp.shape)
    wrong = rng.random(ramp.shape[:2]) < 0.02
    image[wrong] += 60.0
    model = _Ramp(image.astype(np.float32), ramp)
    A = np.stack([np.ones(ramp.size), ramp.ravel()], axis=1) * 255
    plain = np.linalg.lstsq(A, image.ravel(), rcond=None)[0]
    assert abs(plain[0] - truth[0]) * 255 > 1.0            # the outliers do pull plain least squares
    x = ls_fit(model, np.array([0.3, 0.2]), stride=1, max_nfev=50)
    assert abs(x[0] - truth[0]) * 255 < 0.1 and abs(x[1] - truth[1]) * 255 < 0.2
    # the loss it minimizes is lower there than at plain least squares' optimum, and the plain squares the
    # held-out evidence compares are higher (they are plain least squares' own optimum)
    r = [model.simulate(0, v)[0] * 255 - image for v in (x, plain)]
    assert robust_energy(r[0]) < robust_energy(r[1])
    assert residual_energy(model, x[None])[0, 0] > residual_energy(model, plain[None])[0, 0]


def test_robust_energy_is_the_squared_residual_below_its_scale():
    r = np.array([0.1, -0.2, 0.3]) * ROBUST_SCALE
    assert np.isclose(robust_energy(r), np.mean(r ** 2), rtol=0.05)
    assert robust_energy([10 * ROBUST_SCALE]) < 0.05 * (10 * ROBUST_SCALE) ** 2


@pytest.fixture(scope="module")
def near_frame():
    from uw_sil.sim.camera import CameraModel
    from uw_sil.sim.render import Renderer
    from uw_sil.sim.scene import facing_pose

    cam = CameraModel.from_fov(320, 240)
    T = facing_pose(1.2, yaw=0.2, pitch=-0.1)
    with Renderer(camera=cam) as r:
        rr = r.render(T)
    hit = np.isfinite(rr.range)
    return DiagFrame(0, 0, np.zeros((240, 320, 3), np.uint8), rr, cam, T, float(hit.mean()))


def test_reduced_lamp_shading_is_the_block_mean_of_the_full_resolution_one(near_frame):
    """The lamps' Lambert term on a reduced frame: with the block mean of the full-resolution normals, the
    reduced simulation is the block mean of the full-resolution one (up to what varies inside a block);
    normals taken from the block-averaged depth turn the sides of the panel's knobs and levers."""
    from uw_sil.sim.model import Geometry

    lamps = {"artificial_light": {"offset_x": 0.35, "offset_y": -0.15, "half_angle": 0.8, "shape": 2.0,
                                  "fill": 0.3, "power": 0.4, "veil": 0.0}}
    base = [0.3, 0.1, 0.08, 0.06, 0.3, 0.4, 0.05]
    f = 4
    full = EffectModel([reduce_frame(near_frame, 1)], ("artificial_light",), values=lamps)
    want = box_down(full.simulate(0, full.x0(base))[0], f) * 255
    rf = reduce_frame(near_frame, f)
    n_full = Geometry.from_render(near_frame.render, near_frame.camera).normals
    hit = np.isfinite(near_frame.render.range)
    np.testing.assert_allclose(rf.normals[rf.cover >= 1], (box_down(np.where(hit[..., None], n_full, 0), f)
                                                           / np.maximum(rf.cover, 1e-6)[..., None])[rf.cover >= 1],
                               atol=1e-5)
    inner = rf.cover >= 1

    def err(frame):
        m = EffectModel([frame], ("artificial_light",), values=lamps)
        return float(np.sqrt(np.mean((m.simulate(0, m.x0(base))[0] * 255 - want)[inner] ** 2)))

    from dataclasses import replace

    # measured: 1.1 against 9.4 grey levels rms (the lamps kept below saturation: the block mean of a clipped
    # image is not the clipped block mean)
    e_new, e_old = err(rf), err(replace(rf, normals=None))
    assert e_new < 2.0 and e_new < 0.25 * e_old, (e_new, e_old)


def test_a_pose_correction_below_a_quarter_pixel_is_not_named():
    """Warping the geometry by a fraction of a pixel blurs it (bilinear resampling): on a blurred recording
    such a "correction" lowers the residual without any pose error, so it must move the image measurably."""
    from types import SimpleNamespace

    from uw_sil.fit.judges.pose_error import MIN_SHIFT_PX, PoseErrorJudge, image_shift
    from uw_sil.sim.camera import CameraModel

    cam = CameraModel.from_fov(160, 120)
    depth = np.full((120, 160), 1.0, np.float32)
    frame = SimpleNamespace(render=SimpleNamespace(depth=depth, range=depth), camera=cam)
    assert np.isclose(image_shift([frame], {"tx": 1.0 / cam.fx}), 1.0, rtol=1e-3)    # 1 px at 1 m
    assert image_shift([frame], {}) < 1e-9
    judge = PoseErrorJudge()
    current = SimpleNamespace(sel_pf=np.zeros(4))

    def refit(shift):
        return SimpleNamespace(sel_pf=np.zeros(4), statistic={"improvement": 0.08, "margin": 0.02, "shift_px": shift})

    assert judge.accept(refit(0.4 * MIN_SHIFT_PX), current, 0.003)[0] is False
    assert judge.accept(refit(4 * MIN_SHIFT_PX), current, 0.003)[0] is True
