"""The simulated camera: renderer + live parameters + camera noise."""
import numpy as np
import pytest

from uw_sil.sim.camera import CameraModel
from uw_sil.sim.optics import degrade
from uw_sil.sim.params import UnderwaterParams
from uw_sil.sim.scene import facing_pose
from uw_sil.sim.simcam import SimCamera

CAM = CameraModel.from_fov(80, 60)


def test_frame_is_the_underwater_model_of_the_render_and_follows_parameter_changes():
    p = UnderwaterParams(a=(0.4, 0.1, 0.05), b=(0.05, 0.3, 0.4), rho_f=0.1)
    with SimCamera(p, camera=CAM) as cam:
        f = cam.render(facing_pose(2.0))
        np.testing.assert_array_equal(f.image, degrade(f.render.rgb, f.render.range, f.render.depth, p.as_vector()))
        cam.params = UnderwaterParams(a=(0.4, 0.1, 0.05), b=(0.5, 0.3, 0.4), rho_f=0.1)
        assert cam.render(facing_pose(2.0)).image[0, 0, 0] == pytest.approx(0.5)   # water = background


def test_noise_has_the_requested_sigma_and_changes_per_frame():
    with SimCamera(camera=CAM, seed=1) as clean, SimCamera(camera=CAM, noise_sigma=3.0, seed=1) as noisy:
        pose = facing_pose(2.0)
        d1 = noisy.render(pose).image - clean.render(pose).image
        d2 = noisy.render(pose).image - clean.render(pose).image
        assert np.std(d1) * 255 == pytest.approx(3.0, rel=0.05)
        assert not np.array_equal(d1, d2)
        with pytest.raises(ValueError, match="noise_sigma"):
            noisy.noise_sigma = -1.0


def test_a_frame_without_image_has_the_same_geometry_and_no_colour_work():
    """``render(T, image=False)`` (sim_camera when nobody takes its images): the render's depth, range, labels and
    part ids bit for bit as with the image, no image and no clean colour."""
    with SimCamera(camera=CAM, effects="vignetting=strong", noise_sigma=2.0, seed=3) as cam:
        pose = facing_pose(1.7, yaw=0.3)
        full, geo = cam.render(pose), cam.render(pose, image=False)
        assert geo.image is None and geo.render.rgb is None and full.image is not None
        for k in ("depth", "range", "labels", "part_ids"):
            a, b = getattr(full.render, k), getattr(geo.render, k)
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), k
        assert cam.render(pose).image.shape == full.image.shape       # and the next frame has its image again


def test_a_pose_error_is_rendered_from_the_corrected_pose_not_warped():
    """With ``pose_error`` the frame is the render at ``Delta @ T`` (image, depth, labels), bit for bit what a camera
    without the effect renders there; the fit's warp of the recorded view is close to it, not equal."""
    from uw_sil.sim.effects import get_effect
    from uw_sil.sim.model import UnderwaterModel

    p = UnderwaterParams(a=(0.4, 0.1, 0.05), b=(0.05, 0.3, 0.4), rho_f=0.1)
    vals = dict(get_effect("pose_error").defaults(), tx=0.04, ty=-0.03, tz=0.05, ry=-0.015, rz=0.01)
    D = get_effect("pose_error").correction(vals)
    T = facing_pose(1.6, yaw=0.1)
    with SimCamera(p, camera=CAM, effects={"pose_error": vals}) as cam, SimCamera(p, camera=CAM) as plain:
        f, ref = cam.render(T), plain.render(D @ T)
        np.testing.assert_array_equal(f.image, ref.image)
        np.testing.assert_array_equal(f.render.depth, ref.render.depth)
        np.testing.assert_array_equal(cam.render(T, image=False).render.labels, ref.render.labels)
        warped = UnderwaterModel(p, {"pose_error": vals}).degrade(plain.render(T).render, CAM, pose=T)
        moved = np.abs(plain.render(T).image - ref.image).mean()
        assert 0 < np.abs(warped - ref.image).mean() < 0.3 * moved


def test_plan_render_finish_is_render_and_the_draws_follow_the_plans():
    """``render`` is ``finish(*render_job(plan(...)))``; the random draws are taken by ``plan``, in its call order,
    whatever order the frames are then rendered and finished in."""
    T1, T2 = facing_pose(2.0), facing_pose(1.5, yaw=0.2)
    kw = dict(camera=CAM, effects="marine_snow=strong,pose_error=mild", noise_sigma=2.0, seed=4)
    with SimCamera(**kw) as a, SimCamera(**kw) as b:
        first, second = a.render(T1), a.render(T2)
        j1, j2 = b.plan(T1), b.plan(T2)
        r2 = b.render_job(j2)
        r1 = b.render_job(j1)
        np.testing.assert_array_equal(b.finish(*r2).image, second.image)
        np.testing.assert_array_equal(b.finish(*r1).image, first.image)
        assert b.finish(*r1).camera == CAM
