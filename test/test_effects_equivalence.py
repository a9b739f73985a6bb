"""The effects' faster code computes what their code before the speed-ups computed (issue 20, goal 3): the same
effect functions fit effect parameters to real frames, so a change of their output would change fitted values. The
code before is kept in ``effects_reference`` (test-only); each test compares on frames near and far, turned and
pitched, with a seafloor, and lamps beside, above, below and at an angle."""
import os

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import effects_reference as ref                     # noqa: E402  (test/: the code before the speed-ups)
from uw_sil.sim.camera import CameraModel           # noqa: E402
from uw_sil.sim.effects import get_effect           # noqa: E402
from uw_sil.sim.model import Geometry               # noqa: E402
from uw_sil.sim.render import Renderer              # noqa: E402
from uw_sil.sim.scene import facing_pose            # noqa: E402

#: close range, turned, pitched, far (m, yaw, pitch)
POSES = ((1.1, 0.0, 0.0), (1.6, 0.25, -0.08), (2.5, -0.12, 0.1), (3.8, 0.05, -0.06))
#: lamp positions (camera frame): the strong preset's pair, above, below, far to the side, ahead of the camera
LAMPS = ((0.6, -0.3, 0.0), (-0.6, -0.3, 0.0), (0.0, -0.5, 0.1), (0.35, 0.2, 0.0), (1.5, 0.8, 0.0), (-0.3, 0.6, 0.0))


@pytest.fixture(scope="module")
def geoms():
    """The approach's views at 320x240, each without and with the strong seafloor."""
    cam = CameraModel.from_fov(320, 240)
    r = Renderer(camera=cam)
    try:
        out = []
        for d, yaw, pitch in POSES:
            T = facing_pose(d, yaw=yaw, pitch=pitch)
            out.append(Geometry.from_render(r.render(T), cam, T))
    finally:
        r.close()
    ug = get_effect("unmodeled_geometry")
    return out + [ug.add_floor(g, ug.severity("strong")) for g in out]


def _lamp_rigs(lamp) -> list:
    """The presets and rigs turned in, tilted, crossed and off to one side, as the lamp tests compare them."""
    return [lamp.values("strong"), lamp.values("mild"),
            lamp.values({"offset_x": 0.45, "offset_y": 0.25, "toe_in": 0.5, "tilt": 0.4, "half_angle": 0.3,
                         "shape": 4.0, "balance": 0.3, "fill": 0.2}),
            lamp.values({"offset_x": -1.2, "offset_y": -0.6, "toe_in": -0.3, "tilt": -0.5, "balance": 0.0,
                         "cross": 0.5, "cross_y": 0.7, "cross_balance": 0.4, "fill": 0.0, "power": 2.0})]


def test_the_shadow_test_is_the_one_before_bit_for_bit(geoms):
    """The pruning's block minima, band indices and the test's padded depth frame give the same candidate points
    and the same visibility as the code before, for every lamp on every view."""
    from uw_sil.sim.effects import artificial_light as al

    shadowed = 0
    for g in geoms:
        new, old = al._shadow_grid(g), ref._shadow_grid(g)
        np.testing.assert_array_equal(al._block_min(new["zfin"]), ref._block_min(old["zfin"]))
        for L in LAMPS:
            L = np.asarray(L, np.float32)
            vis = al._visibility_on(new, L)
            np.testing.assert_array_equal(vis, ref._visibility_on(old, L))
            shadowed += int((vis < 1).sum())
        for (radii, idx) in old["cand"].items():
            np.testing.assert_array_equal(new["cand"][radii], idx)
    assert shadowed > 1000                                   # the comparison saw shadows


@pytest.mark.parametrize("severity", [{"strength": 0.5, "width": 15.0, "tail": 0.0},
                                      {"strength": 1.5, "width": 40.0, "tail": 0.0},
                                      {"strength": 0.3, "width": 0.5, "tail": 0.0}])
def test_forward_scatter_is_the_blur_before(geoms, severity):
    """Forward scatter's Gaussian part, its levels from the lowest one a pixel takes, the wide ones made for the three
    channels at once with box means from the image's integral where the size does not divide: within 1e-6 of the
    code before (2e-7 measured at 640x480) on every view, for a PSF of the strong preset's width, the widest and the
    narrowest. (Its halo was a four times wider Gaussian then and is Jaffe's kernel now: test_effects.py checks that
    against the exact filter.)"""
    fs = get_effect("forward_scatter")
    values = fs.values(severity)
    for g in geoms:
        r_eff, fx = fs.prepare(g, g.camera)
        D = np.ascontiguousarray(np.moveaxis(g.rgb, 2, 0)) * np.float32(0.8)
        want = D.copy()
        ref.forward_scatter(want, r_eff, fx, values)
        terms = type("Terms", (), {})()
        terms.state, terms.D = {fs.name: (r_eff, fx)}, D
        fs.apply(terms, values, None)
        assert np.abs(D - want).max() <= 1e-6


def test_the_lamps_light_is_the_one_before_bit_for_bit(geoms, monkeypatch):
    """The lamps' light on surfaces (beam, 1/R^2, Lambert, shadows) with |X|^2 and n.X on the hit pixels' planes
    and the faster shadow test equals the light with the einsum over the whole image and the shadow test before,
    for the presets and rigs turned in, tilted, crossed and off to one side."""
    from uw_sil.sim.effects import artificial_light as al

    lamp = get_effect("artificial_light")
    rigs = _lamp_rigs(lamp)
    a = np.array([0.35, 0.1, 0.08], np.float32)
    for g in geoms:
        new = [lamp.illumination(lamp.prepare(g, g.camera), al.LampRig(v), a) for v in rigs]
        with monkeypatch.context() as m:
            m.setattr(al, "_shadow_grid", ref._shadow_grid)
            m.setattr(al, "_visibility_on", ref._visibility_on)
            st = lamp.prepare(g, g.camera)
            idx = st["hit_idx"]
            st["on_hit"]["X2"] = np.einsum("hwk,hwk->hw", g.X, g.X).ravel()[idx]
            st["on_hit"]["nX"] = np.einsum("hwk,hwk->hw", g.normals, g.X).ravel()[idx]
            for v, got in zip(rigs, new):
                np.testing.assert_array_equal(got, lamp.illumination(st, al.LampRig(v), a))


def test_the_seafloor_is_the_one_before_bit_for_bit(geoms):
    """The seafloor by flat indices and its texture's levels by a sort: every array of the geometry it makes (colour,
    depth, range, labels, parts, points, normals, and its finer view's shape) is the one before, for the presets, a
    tilted floor of low contrast and one close below the panel, on every view."""
    ug = get_effect("unmodeled_geometry")
    old = ref.OldFloor()
    cases = [ug.values("strong"), ug.values("mild"), ug.values({"floor_y": -0.5, "tilt": 0.25, "albedo": 0.4,
                                                                "contrast": 0.3}),
             ug.values({"floor_y": -0.36, "tilt": -0.3, "contrast": 1.5})]
    for g in geoms[:len(POSES)]:
        for v in cases:
            a, b = ug.add_floor(g, v), old.add_floor(g, v)
            for name in ("rgb", "depth", "range", "labels", "part_ids", "X", "normals", "hit"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
            fine = g.replace(fine=g)       # a view with a finer one (here itself): the floor's shape added to it
            a, b = ug.add_floor(fine, v).fine, old.add_floor(fine, v).fine
            for name in ("depth", "range", "labels", "part_ids", "X"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_the_normals_are_the_ones_before_bit_for_bit(geoms):
    """The render's normals written per component into one array (0 set on the (H, W) planes before the division)
    are the normals before, bit for bit (the sign of zero too), on every view with and without the seafloor and on
    one with isolated pixels and a pixel of a part of its own (which face the camera)."""
    from uw_sil.sim.model import _normals_from_depth

    g = geoms[0]
    depth, parts = g.depth.copy(), g.part_ids.copy()
    depth[5, 7] = depth[40, 41] = 1.3                   # isolated hits in the water around the panel
    parts[5, 7] = parts[40, 41] = 1
    ys, xs = np.nonzero(g.hit)
    parts[ys[len(ys) // 2], xs[len(xs) // 2]] = 99      # one pixel of its own part on the panel
    cases = [(x.depth, x.part_ids, x.hit) for x in geoms] + [(depth, parts, np.isfinite(depth))]
    for depth, parts, hit in cases:
        new = _normals_from_depth(depth, parts, hit, g.camera, g.xt, g.yt)
        old = ref.normals_from_depth(depth, parts, hit, g.camera, g.xt, g.yt)
        assert new.dtype == old.dtype and new.tobytes() == old.tobytes()
    for y, x in ((5, 7), (40, 41), (ys[len(ys) // 2], xs[len(xs) // 2])):
        assert tuple(new[y, x]) == (0.0, 0.0, -1.0)     # the isolated pixels were there


@pytest.mark.parametrize("severity", ["mild", "strong", {"shot": 1.0, "read": 5.0, "corr": 0.0, "fpn": 0.05,
                                                         "col": 2.0, "row": 1.5},
                                      {"shot": 0.0, "read": 0.0, "fpn": 0.01, "col": 0.5}])
def test_the_camera_noise_is_the_one_before_bit_for_bit(geoms, severity):
    """The camera noise with its standard deviation, fixed-pattern gain and correlated field made in place is the
    noise before, bit for bit, from the same seed (the draws are the same), on images over and under 0..1."""
    from uw_sil.sim.effects.base import effect_rng

    sn = get_effect("sensor_noise")
    values = sn.values(severity)
    for k, g in enumerate(geoms[:3]):
        I = np.ascontiguousarray(np.moveaxis(g.rgb, 2, 0)) * np.float32(1.3) - np.float32(0.1)
        want = I.copy()
        ref.sensor_noise(want, values, effect_rng(k, sn.name))
        terms = type("Terms", (), {})()
        terms.I = I
        sn.apply(terms, values, effect_rng(k, sn.name))
        assert terms.I is I and I.tobytes() == want.tobytes()


def test_the_particles_are_the_ones_before_bit_for_bit(geoms, monkeypatch):
    """Marine snow with its sparse size classes blurred on the tiles their particles reach (the rest of the image: 0)
    is the snow before, bit for bit, in the model's image (lit by the lamps and by the camera's own lamp), at 320x240
    and on 640x480 views, for the presets, the densest and the largest particles (the widest blur)."""
    from uw_sil.sim.effects import marine_snow as ms
    from uw_sil.sim.model import UnderwaterModel

    cam = CameraModel.from_fov(640, 480)
    r = Renderer(camera=cam)
    try:
        big = []
        for d, yaw, pitch in POSES[1:3]:
            T = facing_pose(d, yaw=yaw, pitch=pitch)
            big.append(Geometry.from_render(r.render(T), cam, T))
    finally:
        r.close()
    tiled = []
    real = ms._tiles
    monkeypatch.setattr(ms, "_tiles", lambda *a: tiled.append(real(*a)) or tiled[-1])
    snow = [ms.MarineSnow().values(v) for v in ("mild", "strong")]
    snow += [{"density": 3000.0, "brightness": 3.0, "size": 10.0}, {"density": 800.0, "brightness": 2.0, "size": 0.3}]
    for g in geoms[:len(POSES)] + big:
        for v in snow:
            for lamps in (None, "strong"):
                model = UnderwaterModel(effects={"marine_snow": v} | ({"artificial_light": lamps} if lamps else {}))
                pm = model.prepare(g, g.camera, seed=7)
                new = pm(model.params.as_vector(), model.effect_vector())
                with monkeypatch.context() as m:
                    m.setattr(ms.MarineSnow, "particles", ref.OldSnow.particles)
                    old = model.prepare(g, g.camera, seed=7)(model.params.as_vector(), model.effect_vector())
                assert new.tobytes() == old.tobytes()
    assert sum(t is not None for t in tiled) >= 10            # the tiles were used


def test_the_lamps_irradiance_is_the_one_before_bit_for_bit(geoms):
    """The lamps' irradiance summed on the hit pixels and spread into the image once is the irradiance added into the
    image per lamp and channel before, for the presets and rigs turned in, tilted, crossed and off to one side."""
    from uw_sil.sim.effects import artificial_light as al

    lamp = get_effect("artificial_light")
    rigs = _lamp_rigs(lamp)
    for g in geoms:
        st = lamp.prepare(g, g.camera)
        for v in rigs:
            for a in ([0.35, 0.1, 0.08], [0.0, 0.02, 0.6]):
                a = np.array(a, np.float32)
                new = lamp._irradiance(st, al.LampRig(v), a)
                assert new.tobytes() == ref.OldLamps._irradiance(lamp, st, al.LampRig(v), a).tobytes()


def test_a_geometry_of_the_same_shape_shares_its_terms_bit_for_bit(geoms, monkeypatch):
    """The model's geometry for a seafloor that differs from a kept one in albedo or contrast only shares that one's
    shape terms and the effects' state (the lamps' shadows, forward scatter's ranges): every image equals the one made
    with every geometry prepared from scratch (the code before), on the steps of a least-squares Jacobian (each
    parameter moved in turn, over several iterations, past the kept geometries' limit), with and without a pose
    error (which changes the shape: no sharing across its values), at two seeds."""
    from uw_sil.sim.model import PreparedModel, UnderwaterModel, _Prepared

    shared = []
    real = _Prepared.__init__
    monkeypatch.setattr(_Prepared, "__init__", lambda s, *a, like=None, **kw: shared.append(like is not None)
                        or real(s, *a, like=like, **kw))
    cases = [({"unmodeled_geometry": "strong", "artificial_light": "strong", "forward_scatter": "mild"},
              ("floor_y", "tilt", "albedo", "contrast", "offset_x", "fill", "strength")),
             ({"pose_error": "mild", "unmodeled_geometry": "mild", "artificial_light": "mild"},
              ("tx", "rz", "albedo", "contrast", "floor_y", "half_angle"))]
    for effects, moved in cases:
        model = UnderwaterModel(effects=effects)
        names = [n.split(".")[1] for n in model.effect_param_names()]
        lo, hi = model.effect_bounds()
        base = model.params.as_vector()
        steps = []
        for it in range(3):
            x = np.clip(model.effect_vector() + 0.01 * it * (hi - lo), lo, hi)
            steps.append(x)
            for n in moved:
                j, xs = names.index(n), x.copy()
                xs[j] += 0.004 * (hi[j] - lo[j]) * (-1 if xs[j] > lo[j] else 1)
                steps.append(xs)
        for g in (geoms[0], geoms[2]):
            for seed in (3, 11):
                pm = model.prepare(g, g.camera, seed=seed)
                new = [pm(base, xs) for xs in steps]
                with monkeypatch.context() as m:
                    m.setattr(PreparedModel, "_prep_for", ref.prep_for)
                    pm = model.prepare(g, g.camera, seed=seed)
                    for xs, got in zip(steps, new):
                        assert got.tobytes() == pm(base, xs).tobytes()
    assert sum(shared) >= 24                                 # geometries were shared


def test_the_lamps_terms_kept_per_lamp_give_the_light_and_veil_before_bit_for_bit(geoms):
    """The lamps' light on surfaces and veil made from terms kept per lamp position and axis (its beam, its attenuation
    per channel on top), the veil's integral kept for every geometry of one camera: on the steps of a least-squares
    Jacobian (each lamp parameter and each channel's attenuation moved in turn, then the next iterate) for the rigs the
    lamp tests compare, every light and veil equals the code before's, made from scratch, on every view; the veil's
    states of all views share one camera's cache, as a prepared model's geometries do."""
    from uw_sil.sim.effects import artificial_light as al

    lamp = get_effect("artificial_light")
    old = ref.LampsBefore()
    names = [p.name for p in lamp.params]
    lo, hi = lamp.bounds()
    shared = {}
    kept = 0
    for g in geoms:
        st, before = lamp.prepare(g, g.camera), lamp.prepare(g, g.camera)      # (before: its shadows only kept)
        lamp.share(st, shared)
        for v0 in _lamp_rigs(lamp):
            for it in range(2):
                v = {n: float(np.clip(v0[n] + 0.003 * it * (hi[j] - lo[j]), lo[j], hi[j])) for j, n in enumerate(names)}
                a = np.array([0.35, 0.1, 0.08], np.float32) * np.float32(1 + 0.01 * it)
                steps = [(v, a)]
                for j, n in enumerate(names[:10]):          # the lamps' position, aim, beam, weights
                    step = 0.004 * (hi[j] - lo[j]) * (-1 if v[n] > lo[j] else 1)
                    steps.append(({**v, n: v[n] + step}, a))
                for c in range(3):
                    steps.append((v, a + np.float32(0.002) * (np.arange(3) == c)))
                for vs, at in steps:
                    rig = al.LampRig(vs)
                    E, V = lamp._irradiance(st, rig, at), lamp._veil_unit(st, rig, at)
                    assert E.tobytes() == old._irradiance(before, rig, at).tobytes()
                    assert V.tobytes() == old._veil_unit(before, rig, at).tobytes()
        kept += len(st["_El"]) + len(st["camera"]["_Vl"])
    assert len(shared) == 1 and kept > 100                       # one camera; lamps' terms were kept
