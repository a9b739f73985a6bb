"""Effects of the extended underwater model: registry, parameters, presets, and each effect's signature."""
import math
import os
from types import SimpleNamespace

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from uw_sil.sim.camera import CameraModel
from uw_sil.sim.params import UnderwaterParams
from uw_sil.sim.render import Renderer
from uw_sil.sim.scene import facing_pose
from uw_sil.sim.effects import DEFAULT_SEVERITY, EFFECT_ORDER, EFFECTS, STAGES, get_effect, parse_effects
from uw_sil.sim.model import UnderwaterModel, effect_params_to_flat, flat_to_effect_params

NAMES = {"artificial_light", "forward_scatter", "port_refraction", "backscatter_coefficient", "vignetting",
         "sensor_noise", "marine_snow", "camera_response", "unmodeled_geometry", "pose_error", "compression"}
P = UnderwaterParams(a=(0.35, 0.1, 0.08), b=(0.06, 0.3, 0.4), rho_f=0.05)


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(camera=CameraModel.from_fov(160, 120))
    yield r
    r.close()


@pytest.fixture(scope="module")
def frames(renderer):
    poses = {"near": facing_pose(1.5), "mid": facing_pose(2.5, yaw=0.1), "far": facing_pose(3.5)}
    return {k: (T, renderer.render(T)) for k, T in poses.items()}


def degrade(effects, frame, cam, seed=0, params=P):
    T, rr = frame
    return UnderwaterModel(params, effects).degrade(rr, cam, rng=np.random.default_rng(seed), pose=T)


# ---------------------------------------------------------------------------- registry and parameters


def test_registry_names_and_stages():
    assert set(EFFECTS) == NAMES
    assert [STAGES.index(EFFECTS[n].stage) for n in EFFECT_ORDER] == sorted(STAGES.index(EFFECTS[n].stage)
                                                                             for n in EFFECT_ORDER)
    for name, e in EFFECTS.items():
        assert e.name == name and get_effect(name) is e
        assert e.stage in STAGES
        assert set(e.severities) == {"mild", "strong"}
        assert 1 <= len(e.params) <= 16
        assert isinstance(e.invertible, bool) and isinstance(e.random_per_frame, bool)
        for level in ("mild", "strong"):
            e.check(e.severity(level))                       # presets lie inside the bounds


def test_diagnosis_leaves_added_surfaces_out_of_noise_statistics(frames, renderer):
    """The pixels a fitted seafloor adds (with the noise statistics' 24 px margin) are what the noise is then
    judged without: below the horizon, never the panel's own pixels' interior."""
    from types import SimpleNamespace

    from uw_sil.fit.residuals import added_surface as _added_surface

    T, rr = frames["far"]
    f = SimpleNamespace(render=rr, camera=renderer.camera, pose=T)
    m = _added_surface(f, {"unmodeled_geometry": EFFECTS["unmodeled_geometry"].severity("strong")})
    assert m.mean() > 0.1 and np.nonzero(m)[0].min() > renderer.camera.cy - 24
    assert not _added_surface(f, {"unmodeled_geometry": {"floor_y": -5.0}})[: int(renderer.camera.cy) - 24].any()


@pytest.mark.parametrize("name", sorted(NAMES))
def test_vector_bounds_round_trip(name):
    e = EFFECTS[name]
    lo, hi = e.bounds()
    assert lo.shape == hi.shape == (len(e.params),) and np.all(lo < hi)
    for level in ("mild", "strong"):
        v = e.severity(level)
        x = e.vector(v)
        assert np.all((x >= lo) & (x <= hi))
        assert e.from_vector(x) == v
    x = lo + 0.37 * (hi - lo)
    np.testing.assert_allclose(e.vector(e.from_vector(x)), x)
    with pytest.raises(ValueError, match=name):
        e.values({e.params[0].name: hi[0] + 1.0})
    with pytest.raises(ValueError, match="no parameter"):
        e.values({"bogus": 1.0})


def test_parse_effects():
    d = parse_effects("artificial_light=strong,vignetting")
    assert list(d) == ["artificial_light", "vignetting"]            # composition order
    assert d["artificial_light"] == EFFECTS["artificial_light"].severity("strong")
    assert d["vignetting"] == EFFECTS["vignetting"].severity(DEFAULT_SEVERITY)
    d = parse_effects("vignetting=mild, vignetting.k1=-0.4")
    assert d["vignetting"]["k1"] == -0.4 and d["vignetting"]["k2"] == EFFECTS["vignetting"].severity("mild")["k2"]
    assert parse_effects("") == {}
    with pytest.raises(ValueError, match="fog_of_war"):
        parse_effects("vignetting,fog_of_war=mild")
    with pytest.raises(ValueError, match="'medium'.*vignetting|vignetting.*'medium'"):
        parse_effects("vignetting=medium")
    with pytest.raises(ValueError, match="k9"):
        parse_effects("vignetting.k9=1")
    with pytest.raises(ValueError, match="vignetting.k1"):
        parse_effects("vignetting.k1=5")
    with pytest.raises(ValueError, match="not a number"):
        parse_effects("vignetting.k1=abc")


def test_flat_params_round_trip():
    effects = parse_effects("artificial_light=mild,sensor_noise=strong")
    flat = effect_params_to_flat(effects)
    assert flat["artificial_light.offset_x"] == effects["artificial_light"]["offset_x"]
    assert len(flat) == len(EFFECTS["artificial_light"].params) + len(EFFECTS["sensor_noise"].params)
    flat.update({"a_r": 0.3, "fog_mode": "exp2", "qos_overrides./x.depth": 3})      # ignored keys
    assert flat_to_effect_params(flat) == effects
    with pytest.raises(ValueError, match="nope"):
        flat_to_effect_params({"vignetting.nope": 1.0})


# ---------------------------------------------------------------------------- signatures


def test_vignetting_radial_and_frame_invariant(frames, renderer):
    cam = renderer.camera
    spec = {"vignetting": {"k1": -0.5, "k2": 0.1}}
    ratios = []
    for key in ("near", "far"):
        base = degrade({}, frames[key], cam)
        ratios.append(degrade(spec, frames[key], cam) / base)
    np.testing.assert_allclose(ratios[0], ratios[1], rtol=1e-5)           # same in every frame, any range
    V = ratios[0][..., 1]
    np.testing.assert_allclose(V, V[::-1, ::-1], rtol=1e-4)               # symmetric about the centre
    assert V[60, 80] > 0.999 and abs(V[0, 0] - (1 - 0.5 + 0.1)) < 0.02    # 1 at the centre, 1+k1+k2 at corners
    # a lens only loses light away from its centre: coefficients that would brighten the corners are capped at 1
    bright = degrade({"vignetting": {"k1": 0.45, "k2": -0.2}}, frames["near"], cam)
    np.testing.assert_array_equal(bright, degrade({}, frames["near"], cam))
    mixed = degrade({"vignetting": {"k1": 0.4, "k2": -0.6}}, frames["near"], cam) / degrade({}, frames["near"], cam)
    assert mixed[..., 1].max() <= 1.0 and mixed[0, 0, 1] < 0.85          # (1 + 0.4 rho^2 - 0.6 rho^4: dark corners)


def test_artificial_light_multiplicative_and_falling_with_distance(frames, renderer):
    cam = renderer.camera
    lamp = {"offset_x": 0.3, "offset_y": 0.0, "balance": 0.5, "half_angle": 1.2, "fill": 0.0, "veil": 0.0,
            "power": 0.3}                                              # nothing saturates
    gains = {}
    for key in ("near", "far"):
        T, rr = frames[key]
        model = UnderwaterModel(P, {"artificial_light": lamp})
        base = UnderwaterModel(P).degrade(rr, cam)
        img = model.degrade(rr, cam)
        water = ~np.isfinite(rr.range)
        np.testing.assert_array_equal(img[water], base[water])            # no veil: open water unaffected
        # multiplicative on the radiance: (I - B) scales by the illumination
        tr = np.exp(-np.asarray(P.a)[None, None] * rr.range[..., None]) * np.exp(-(P.rho_f * rr.depth) ** 2)[..., None]
        Bk = np.asarray(P.b) * (1 - tr)
        plate = (np.abs(rr.depth - float(T[2, 3])) < 2e-3) & (np.hypot(*np.mgrid[-59.5:60.5, -79.5:80.5]) < 6)
        plate &= lamp_visibility(rr, cam, T, (0.3, 0, 0)) * lamp_visibility(rr, cam, T, (-0.3, 0, 0)) == 1
        assert plate.sum() > 20                      # the plate's front face near the centre, outside the shadows
        g = (img - Bk)[plate].sum(axis=0) / (base - Bk)[plate].sum(axis=0)
        gains[key] = g[:2]                                                # yellow paint: no blue to measure
    def on_axis(d):                      # two lamps at (+-0.3, 0, 0) lighting the plate point (0, 0, d)
        R = np.hypot(d, 0.3)
        beam = np.exp(-np.log(2) * (np.arctan2(0.3, d) / 1.2) ** 2)
        return beam * (d / R) / R ** 2 * np.exp(-np.asarray(P.a[:2]) * R)
    np.testing.assert_allclose(gains["far"] / gains["near"], on_axis(3.5) / on_axis(1.5), rtol=0.03)
    assert gains["far"][0] < gains["far"][1]                             # red suffers more on the lamp path


def lamp_visibility(rr, cam, T, L):
    """The lamp effect's cast-shadow visibility (H, W) of a lamp at ``L`` (camera frame) for render ``rr``."""
    from uw_sil.sim.effects.artificial_light import ArtificialLight
    from uw_sil.sim.model import Geometry

    st = ArtificialLight().prepare(Geometry.from_render(rr, cam, T), cam)
    return ArtificialLight._visibility(st, np.asarray(L, np.float32))


def _block_scene(cam, z_wall=2.0, z_block=1.8, half=0.1):
    """A wall facing the camera at ``z_wall`` with a square block (side ``2 half``) standing ``z_wall - z_block``
    in front of it on the optical axis: depth, range and part ids of the view (no render: exact geometry)."""
    from uw_sil.sim.model import Geometry

    h, w = cam.height, cam.width
    xt = (np.arange(w) - cam.cx) / cam.fx
    yt = (np.arange(h) - cam.cy) / cam.fy
    XT, YT = np.meshgrid(xt, yt)
    on_block = (np.abs(XT * z_block) <= half) & (np.abs(YT * z_block) <= half)
    depth = np.where(on_block, z_block, z_wall).astype(np.float32)
    rng = (depth * np.sqrt(1 + XT ** 2 + YT ** 2)).astype(np.float32)
    parts = np.where(on_block, 2, 1).astype(np.uint16)
    geom = Geometry(cam, np.full((h, w, 3), 0.5, np.float32), depth, rng, part_ids=parts)
    return geom, XT, YT, on_block


def _floor_scene(cam, height=0.5, block=False):
    """A seafloor ``height`` below the camera (y down), seen level (no render: exact geometry; labels 2), with
    ``block``: a box 0.2 m wide and 0.25 m high standing on it 1.5 m ahead, its face towards the camera."""
    from uw_sil.sim.model import Geometry

    h, w = cam.height, cam.width
    XT, YT = np.meshgrid((np.arange(w) - cam.cx) / cam.fx, (np.arange(h) - cam.cy) / cam.fy)
    with np.errstate(divide="ignore"):
        depth = np.where(YT > 0.01, height / np.maximum(YT, 1e-9), np.inf)
    labels = np.where(np.isfinite(depth), 2, 0)
    parts = np.where(np.isfinite(depth), 0xFFFF, 0)
    if block:
        zb = 1.5
        face = (np.abs(XT * zb) <= 0.1) & (YT * zb >= height - 0.25) & (YT * zb <= height) & (zb < depth)
        depth, labels, parts = np.where(face, zb, depth), np.where(face, 1, labels), np.where(face, 1, parts)
    depth = depth.astype(np.float32)
    rng = (depth * np.sqrt(1 + XT ** 2 + YT ** 2)).astype(np.float32)
    return Geometry(cam, np.full((h, w, 3), 0.5, np.float32), depth, rng, labels=labels,
                    part_ids=parts.astype(np.uint16))


def test_the_seafloor_casts_no_shadow_on_itself_but_takes_one_from_what_stands_on_it():
    """A plane cannot hide a lamp from itself: the segment from a floor point to a lamp on the camera's side of the
    floor stays on that side, and a lamp below the floor gives it no light (Lambert). The screen-space test on a
    floor seen at grazing angles changes its depth by more than the bias from one pixel row to the next (8 cm at
    3 m with the camera 0.5 m above it), and samples rounded to a pixel found the floor in front of them: with
    the camera 0.5 m above it and a lamp 0.6 m beside and 0.3 m below the camera, 3,759 of 320x240 pixels.
    Now none, for lamps above, beside, at the floor's height and below it; a box standing on the floor still
    throws its shadow on it, to the side away from the lamp."""
    from uw_sil.sim.effects.artificial_light import _shadow_grid, _visibility_on

    cam = CameraModel.from_fov(320, 240, 70.0)
    for height in (0.5, 0.85):
        g = _shadow_grid(_floor_scene(cam, height))
        for L in ((0.6, -0.3, 0.0), (0.6, 0.3, 0.0), (1.5, 0.8, 0.0), (0.0, 0.45, 0.0), (-0.3, 0.8, 0.1),
                  (0.2, 1.0, 0.0)):
            assert (_visibility_on(g, np.asarray(L, np.float32)) == 1).all(), (height, L)
    geom = _floor_scene(cam, 0.5, block=True)
    g = _shadow_grid(geom)
    u = np.arange(cam.width)[None, :].repeat(cam.height, 0)
    on_floor = geom.labels == 2
    for ox in (0.6, -0.6):
        vis = _visibility_on(g, np.asarray((ox, 0.0, 0.0), np.float32))
        dark = (vis < 1) & on_floor
        assert dark.sum() > 50
        # behind the box, on the side away from the lamp
        assert (np.sign(u[dark] - cam.cx) == -np.sign(ox)).mean() > 0.9


def test_a_seafloor_on_a_reduced_frame_is_added_to_its_finer_view_too(renderer, monkeypatch):
    """On a reduced frame the lamps' shadows are tested on the finer view (``Geometry.fine``); a seafloor the model
    adds must be in that view as well, or the shadow test runs on the reduced frame, without the floor's relief to
    the panel, wherever a seafloor is fitted (it was: ``replace`` drops the finer view). That view is made when it
    is first read (a floor fitted without lamps never needs it), with the floor's shape only: its depth, points and
    labels those of the floor with its colour."""
    from uw_sil.sim.effects.unmodeled_geometry import UnmodeledGeometry
    from uw_sil.sim.model import Geometry

    T = facing_pose(2.0, pitch=0.1)
    cam = renderer.camera                                          # 160x120, the finer view
    small = cam.binned(2)
    fine = Geometry.from_render(renderer.render(T), cam, T)
    coarse = Geometry(small, np.zeros((small.height, small.width, 3), np.float32),
                      fine.depth[::2, ::2], fine.range[::2, ::2], labels=fine.labels[::2, ::2],
                      part_ids=fine.part_ids[::2, ::2], pose=T, fine=fine)
    ug = UnmodeledGeometry()
    floor = {**{p.name: p.default for p in ug.params}, **ug.severities["strong"]}
    calls = []
    real = UnmodeledGeometry.add_floor
    monkeypatch.setattr(UnmodeledGeometry, "add_floor",
                        lambda self, g, *a, **kw: calls.append(g) or real(self, g, *a, **kw))
    out = ug.add_floor(coarse, floor)
    assert calls == [coarse] and out.has_finer_view                 # the finer view not made yet
    assert out.fine is not None and out.fine.shape == fine.shape and calls[1] is fine
    assert out.fine is out.fine and len(calls) == 2                # made once
    share, share_fine = (out.labels == 2).mean(), (out.fine.labels == 2).mean()
    assert share > 0.1 and abs(share - share_fine) < 0.02
    whole = real(ug, fine, floor)
    for name in ("labels", "part_ids", "depth", "range", "X"):
        np.testing.assert_array_equal(getattr(out.fine, name), getattr(whole, name))


def test_a_pose_correction_on_a_reduced_frame_moves_its_finer_view_too(renderer):
    """The same for the pose error's warp: the finer view is seen from the moved camera (made when read), so the
    lamps' shadows are tested on the corrected view at twice the resolution; its depth, labels and points are those
    of the whole warp of the finer view."""
    from uw_sil.sim.effects.pose_error import rotation_matrix, warp_geometry
    from uw_sil.sim.model import Geometry

    T = facing_pose(2.0)
    cam = renderer.camera
    small = cam.binned(2)
    fine = Geometry.from_render(renderer.render(T), cam, T)
    coarse = Geometry(small, np.zeros((small.height, small.width, 3), np.float32), fine.depth[::2, ::2],
                      fine.range[::2, ::2], labels=fine.labels[::2, ::2], part_ids=fine.part_ids[::2, ::2], pose=T,
                      fine=fine)
    R, t = rotation_matrix((0.0, 0.02, 0.01)), np.array([0.05, -0.03, 0.04])
    out = warp_geometry(coarse, R, t)
    assert out.has_finer_view and out.fine.shape == fine.shape
    whole = warp_geometry(fine, R, t)
    for name in ("labels", "part_ids", "depth", "range", "X"):
        np.testing.assert_array_equal(getattr(out.fine, name), getattr(whole, name))
    moved = (out.fine.labels[::2, ::2] != fine.labels[::2, ::2]).mean()
    assert moved > 0.01 and ((out.fine.labels[::2, ::2] != out.labels).mean() < 0.02)


def test_a_pose_fit_carries_the_lamps_shadows_through_its_warps():
    """Within ``carrying_shadows`` (the pose refit's least-squares fit) a warped view takes the lamps' shadows of the
    view it was warped from, at its source pixels, instead of testing itself again (about 10 of the 14 s of a
    lamp-lit pose refit); warps of warps go back to the first view. Outside it nothing is carried. For a correction
    of 5 cm the carried shadows are the view's own on all but a sliver of the wall (the lamps move with the camera
    against the scene, so the shadows move by a fraction of the correction: here 5 cm x 0.2 m / 1.8 m, a pixel)."""
    from uw_sil.sim.effects.artificial_light import ArtificialLight
    from uw_sil.sim.effects.pose_error import carrying_shadows, rotation_matrix, warp_geometry

    cam = CameraModel.from_fov(320, 240, 70.0)
    geom, _, _, _ = _block_scene(cam)
    eff = ArtificialLight()
    L = np.array([0.5, 0.0, 0.0], np.float32)
    R, t = rotation_matrix((0.0, 0.01, 0.0)), np.array([0.05, 0.0, 0.0])
    own = warp_geometry(geom, R, t)
    assert own.carried_from is None
    with carrying_shadows():
        moved = warp_geometry(geom, R, t)
        twice = warp_geometry(moved, R, t)
    src, idx, hit = moved.carried_from
    assert src is geom and twice.carried_from[0] is geom
    # a warp of a warp: its source pixels are those of the first view (the second warp's own, composed)
    with carrying_shadows():
        plain = moved.replace(X=moved.X, normals=moved.normals)          # the same view, nothing carried
        again = warp_geometry(plain, R, t)
    np.testing.assert_array_equal(twice.carried_from[1], idx.ravel()[again.carried_from[1]])
    np.testing.assert_array_equal(twice.carried_from[2], again.carried_from[2] & hit.ravel()[again.carried_from[1]])
    v_src = eff._shadows(eff.prepare(geom, cam), L)
    v_moved = eff._shadows(eff.prepare(moved, cam), L)
    np.testing.assert_array_equal(v_moved[hit], v_src.ravel()[idx[hit]])
    assert (v_moved[~hit] == 1).all() and (v_src < 0.5).sum() > 100
    v_own = eff._shadows(eff.prepare(own, cam), L)
    differ = (np.abs(v_moved - v_own) > 0.5).mean()
    assert differ < 0.01, differ


def test_artificial_light_casts_shadows_that_move_with_the_lamp():
    """A lamp beside the camera: the block hides it from a strip of the wall on the side away from the lamp, as
    wide as the geometry says (the shadow of the block's edge minus the part of the wall the block hides from the
    camera); the mirrored lamp throws it to the other side; a lamp at the camera throws none the camera can see;
    shadowed wall gets the fill light only."""
    from uw_sil.sim.effects.artificial_light import ArtificialLight, LampRig

    cam = CameraModel.from_fov(320, 240, 70.0)
    geom, XT, YT, on_block = _block_scene(cam)
    eff = ArtificialLight()
    st = eff.prepare(geom, cam)
    row = cam.height // 2
    wall_x = XT[row] * 2.0                                   # where each column of the row meets the wall
    for ox in (1.0, -1.0):
        vis = eff._visibility(st, np.array([ox, 0.0, 0.0], np.float32))
        # the block's edge facing away from the lamp at x_e = -sign(ox) 0.1, z 1.8: its shadow on the wall at
        # z 2 reaches x = ox + (x_e - ox) 2 / 1.8; the camera sees the wall from x_e 2 / 1.8 outwards
        x_e = -np.sign(ox) * 0.1
        x_far, x_near = ox + (x_e - ox) * 2.0 / 1.8, x_e * 2.0 / 1.8
        lo, hi = sorted((x_far, x_near))
        strip = (~on_block[row]) & (wall_x > lo) & (wall_x < hi)
        # the shadow's far edge comes from rays that graze the block's edge: they pass in front of it over a
        # centimetre or two, which the depth bias and the sampling along the ray can miss, so it may end up to
        # 4 px (3.5 cm of wall here) short; the rest of the strip is black, its edges softened over 3x3 pixels
        far = 0.04 if ox > 0 else 0.0
        near = 0.0 if ox > 0 else 0.04
        inner = strip & (wall_x > lo + 0.01 + far) & (wall_x < hi - 0.01 - near)
        assert inner.sum() >= 5 and (vis[row][inner] == 0).all()
        lit = (~on_block[row]) & ((wall_x < lo - 0.01) | (wall_x > hi + 0.01))
        assert (vis[row][lit] == 1).all()                                    # nowhere else on the row
        assert strip.sum() - 4 <= (vis[row] < 0.5).sum() <= strip.sum()       # the strip's width, within 4 px
        assert (vis[on_block] == 1).all()                                    # the block's own face is lit
    assert (eff._visibility(st, np.zeros(3, np.float32)) == 1).all()          # the lamp at the eye
    # in the effect: a lamp-only light (fill 0) leaves the shadow black; fill 0.3 leaves 0.3 of the uniform light
    vals = {p.name: p.default for p in eff.params}
    vals.update(offset_x=1.0, offset_y=0.0, balance=0.0, half_angle=1.4, power=1.0)
    a = np.array([0.1, 0.1, 0.1], np.float32)
    vis = eff._visibility(st, np.array([1.0, 0.0, 0.0], np.float32))
    for fill in (0.0, 0.3):
        L = eff.illumination(st, LampRig({**vals, "fill": fill}), a)
        np.testing.assert_allclose(L[:, vis == 0], fill, atol=1e-6)
        assert (L[:, (vis == 1) & ~on_block] > fill + 0.1).all()


def test_the_shadow_test_skips_only_points_it_would_find_lit(frames, renderer):
    """The shadow test first drops the points that no occluder can reach (a depth erosion over the lamp's parallax
    radius): with every point tested instead, the visibility is the same, on the panel near, tilted and far, for
    lamps beside, above, below, far to the side of, ahead of, behind and at the camera, on two block scenes, on the
    panel above a seafloor and on a block standing on a seafloor. (A radius taken from the occluder's thickness,
    0.3 m, instead of the deepest sample, fails on the deeper block; one taken at the band's farthest depth instead
    of its nearest fails too.) One grid serves every lamp, as the candidates of a fit share it: the points kept for
    testing depend on the lamp only through the radii and are kept per set of radii, so lamps mirrored or moved at
    the same distance reuse them."""
    from uw_sil.sim.effects.artificial_light import _shadow_grid, _visibility_on
    from uw_sil.sim.model import Geometry

    cam = renderer.camera
    from uw_sil.sim.effects.unmodeled_geometry import UnmodeledGeometry

    cam = renderer.camera
    ug = UnmodeledGeometry()
    floor = {**{p.name: p.default for p in ug.params}, **ug.severities["strong"]}
    geoms = [Geometry.from_render(rr, cam, T) for T, rr in frames.values()]
    # the panel above a seafloor (its points are tested against everything but the floor)
    geoms += [ug.add_floor(g, dict(floor, floor_y=y)) for g in geoms for y in (-0.4, -0.85)]
    cam2 = CameraModel.from_fov(320, 240, 70.0)
    geoms.append(_block_scene(cam2)[0])
    # a block 0.6 m in front of the wall: its shadow reaches ~50 px from it, found by samples 0.3-0.5 m deep
    geoms.append(_block_scene(cam2, z_block=1.4)[0])
    geoms.append(_floor_scene(cam2, block=True))
    grids = [_shadow_grid(g) for g in geoms]
    shadowed = 0
    for g in grids:
        # (the lamp at the camera first: its radius is the smallest, its points to test the fewest)
        for L in ((0.0, 0.0, 0.0), (0.6, -0.3, 0.0), (-0.35, 0.0, 0.0), (1.5, 0.8, 0.0), (0.0, -0.5, 0.1),
                  (0.35, 0.0, 0.0), (0.0, 0.6, 0.0), (0.6, 0.2, 0.0), (0.5, -0.2, -0.4), (-0.4, 0.1, 0.4)):
            L = np.asarray(L, np.float32)
            fast = _visibility_on(g, L)
            np.testing.assert_array_equal(fast, _visibility_on(g, L, prune=False))
            shadowed += int((fast < 1).sum())
    assert shadowed > 100                                    # the comparison saw shadows


def test_shadows_on_a_reduced_frame_are_the_mean_over_each_block_bit_for_bit(frames, renderer, monkeypatch):
    """On a reduced frame the shadow test runs on the finer grid and each block gets the mean over its hit pixels.
    The code sums only the blocks around the shadows (elsewhere the mean is 1): that must give exactly the mean
    the whole grid's sum gives (numpy sums a part of a grid one block wide in another order; a last-bit difference
    changed a diagnosis's fitted lamp offset in its 4th digit), for many lamp positions on the panel renders and
    on two block scenes, and for shadow maps of soft values in boxes of every width and height up to 6 blocks."""
    import uw_sil.sim.effects.artificial_light as al
    from uw_sil.sim.effects.artificial_light import ArtificialLight, _shadow_grid, _visibility_on
    from uw_sil.sim.model import Geometry

    geoms = [Geometry.from_render(rr, renderer.camera, T) for T, rr in frames.values()]
    cam2 = CameraModel.from_fov(320, 240, 70.0)
    geoms += [_block_scene(cam2)[0], _block_scene(cam2, z_block=1.4)[0]]
    rng = np.random.default_rng(0)
    soft = 0
    for geom in geoms:
        g = _shadow_grid(geom)                   # the full grid, seen as the finer grid of a half-size frame
        h, w = g["z"].shape[0] // 2, g["z"].shape[1] // 2
        g = dict(g, sub=2, hit_blocks=g["hit"].reshape(h, 2, w, 2).sum(axis=(1, 3), dtype=np.float32))
        for L in rng.uniform((-1.2, -0.8, -0.1), (1.2, 0.8, 0.1), (40, 3)).astype(np.float32):
            vis = _visibility_on(g, L)
            lit = np.where(g["hit"], vis, np.float32(0)).reshape(h, 2, w, 2).sum(axis=(1, 3), dtype=np.float32)
            want = np.where(g["hit_blocks"] > 0, lit / np.maximum(g["hit_blocks"], 1), np.float32(1)).astype(
                np.float32)
            got = ArtificialLight._visibility({"shadow": g}, L)
            np.testing.assert_array_equal(got, want)
            soft += int(((want > 0) & (want < 1)).sum())
    assert soft > 1000                                   # blocks partly in shadow were compared
    # shadow maps in boxes of each size (soft values k/9 as the 3x3 soft edges give), at random places
    for bh in range(1, 7):
        for bw in range(1, 7):
            vis = np.ones(g["z"].shape, np.float32)
            r, c = 2 * rng.integers(0, h - bh), 2 * rng.integers(0, w - bw)
            vis[r:r + 2 * bh, c:c + 2 * bw] = rng.integers(0, 10, (2 * bh, 2 * bw)) / np.float32(9)
            monkeypatch.setattr(al, "_visibility_on", lambda g, L, vis=vis: vis)
            lit = np.where(g["hit"], vis, np.float32(0)).reshape(h, 2, w, 2).sum(axis=(1, 3), dtype=np.float32)
            want = np.where(g["hit_blocks"] > 0, lit / np.maximum(g["hit_blocks"], 1), np.float32(1))
            np.testing.assert_array_equal(ArtificialLight._visibility({"shadow": g}, None), want)


def test_artificial_light_tilt_aims_the_beam_below_the_optical_axis():
    """``tilt`` pitches the beam axes (y down): on a wall 2 m ahead, one narrow lamp beside the camera lights the
    wall brightest where its axis meets it, ``2 tan(tilt)`` below the lamp's height, i.e. ``fy tan(tilt)`` pixels
    below the principal point (within 4 px: the 1/R² and Lambert terms pull the peak a little towards the lamp);
    the column of the peak stays the lamp's; ``tilt`` 0 keeps the beam level. The veil follows the beam: more of it
    below the principal point than above when the beam is aimed down."""
    from uw_sil.sim.effects.artificial_light import ArtificialLight, LampRig

    cam = CameraModel.from_fov(320, 240, 70.0)
    geom = _block_scene(cam, half=0.0)[0]                    # the wall alone
    eff = ArtificialLight()
    st = eff.prepare(geom, cam)
    vals = {p.name: p.default for p in eff.params}
    vals.update(offset_x=0.3, offset_y=0.0, balance=0.0, half_angle=0.15, shape=2.0, power=1.0, fill=0.0)
    a = np.zeros(3, np.float32)
    col = int(round(cam.cx + cam.fx * 0.3 / 2.0))            # the lamp's column on the wall
    for tilt in (0.0, 0.25, -0.2):
        L = eff.illumination(st, LampRig({**vals, "tilt": tilt}), a)[1]
        r, c = np.unravel_index(int(np.argmax(L)), L.shape)
        assert abs(r - (cam.cy + cam.fy * np.tan(tilt))) <= 4, (tilt, r)
        assert abs(c - col) <= 4, (tilt, c)
    V = {t: eff.veil_field(st, LampRig({**vals, "tilt": t}), a, 0.05)[1] for t in (0.0, 0.3)}
    half = cam.height // 2
    low, high = (V[0.3][half:].sum() / V[0.3][:half].sum()), (V[0.0][half:].sum() / V[0.0][:half].sum())
    assert low > 1.2 * high, (low, high)


def test_artificial_light_ahead_of_or_behind_the_camera_moves_the_inverse_square_falloff():
    """``offset_z`` puts the lamps ahead of (> 0) or behind (< 0) the camera's plane. On walls 1.2 and 4 m ahead,
    one lamp 0.3 m beside the camera lights every pixel of the wall as the module's formula says for a lamp at
    ``(0.3, -0.1, offset_z)`` (beam, Lambert and ``(R0 / R)^2`` worked out here from the wall's points, no water):
    0.2 m behind the camera the near wall gets (1.2 / 1.4)^2 / (4 / 4.2)^2 = 0.81 of the light against the far wall
    that a lamp in the camera's plane gives it, and 0.2 m ahead more. The cross's lamps move with the pair."""
    from uw_sil.sim.effects.artificial_light import ArtificialLight, LampRig

    cam = CameraModel.from_fov(320, 240, 70.0)
    eff = ArtificialLight()
    vals = {p.name: p.default for p in eff.params}
    vals.update(offset_x=0.3, offset_y=-0.1, toe_in=0.1, tilt=0.05, balance=0.0, half_angle=0.6, shape=2.0,
                power=1.0, fill=0.0)
    a = np.zeros(3, np.float32)
    mid = {}
    for d in (1.2, 4.0):
        geom, XT, YT, _ = _block_scene(cam, z_wall=d, half=0.0)
        st = eff.prepare(geom, cam)
        X = np.stack([XT * d, YT * d, np.full_like(XT, d)], axis=-1)
        for oz in (0.0, -0.2, 0.2):
            rig = LampRig({**vals, "offset_z": oz})
            np.testing.assert_allclose(rig.pos[0], (0.3, -0.1, oz), atol=1e-7)
            v = X - rig.pos[0]
            R = np.linalg.norm(v, axis=-1)
            theta = np.arccos(np.clip(v @ rig.axis[0] / R, -1, 1))
            want = np.exp(-np.log(2) * (theta / 0.6) ** 2) * (d - oz) / R * (2.0 / R) ** 2
            L = eff.illumination(st, rig, a)
            np.testing.assert_allclose(L[1], want, rtol=2e-4)
            mid[d, oz] = float(L[1][cam.height // 2, int(round(cam.cx + cam.fx * 0.3 / d))])
    rel = {oz: (mid[1.2, oz] / mid[4.0, oz]) / (mid[1.2, 0.0] / mid[4.0, 0.0]) for oz in (-0.2, 0.2)}
    assert rel[-0.2] == pytest.approx((1.2 / 1.4) ** 2 / (4 / 4.2) ** 2, rel=0.01)
    assert rel[0.2] == pytest.approx((1.2 / 1.0) ** 2 / (4 / 3.8) ** 2, rel=0.01)
    rig = LampRig({**vals, "cross": 0.5, "cross_y": 0.4, "offset_z": -0.2})
    np.testing.assert_allclose(rig.pos[2:, 2], -0.2, atol=1e-7)


def test_artificial_light_cross_adds_a_top_and_a_bottom_lamp_aimed_at_the_work_area():
    """With ``cross`` the rig has a top lamp (``cross_balance`` 0) or a bottom lamp (1) on the camera's vertical,
    ``cross_y`` from it, aimed at the pair's work area 2 m ahead: beyond it, on a wall 4 m ahead, a narrow top lamp
    lights the wall brightest ``fy (cross_y (4 - 2) / 2) / 4`` pixels below the principal point and a bottom lamp as
    far above it (within 4 px), both on the camera's column. The shares are shares: the light with ``cross`` 0.3 is
    0.7 of the pair's plus 0.3 of the cross's, and with ``cross`` 0 the cross's height and balance change
    nothing."""
    from uw_sil.sim.effects.artificial_light import ArtificialLight, LampRig

    cam = CameraModel.from_fov(320, 240, 70.0)
    geom = _block_scene(cam, z_wall=4.0, half=0.0)[0]
    eff = ArtificialLight()
    st = eff.prepare(geom, cam)
    vals = {p.name: p.default for p in eff.params}
    vals.update(offset_x=0.5, offset_y=0.0, tilt=0.0, balance=0.5, half_angle=0.15, shape=2.0, power=1.0, fill=0.0,
                cross_y=0.4)
    a = np.zeros(3, np.float32)
    dy = cam.fy * (0.4 * (4.0 - 2.0) / 2.0) / 4.0
    for cb, row in ((0.0, cam.cy + dy), (1.0, cam.cy - dy)):
        L = eff.illumination(st, LampRig({**vals, "cross": 0.7, "cross_balance": cb}), a)[1]
        L = L - 0.3 * eff.illumination(st, LampRig({**vals, "cross": 0.0}), a)[1]      # the cross's part alone
        r, c = np.unravel_index(int(np.argmax(L)), L.shape)
        assert abs(r - row) <= 4 and abs(c - cam.cx) <= 4, (cb, r, c, row)
    pair = eff.illumination(st, LampRig({**vals, "cross": 0.0}), a)
    cross = eff.illumination(st, LampRig({**vals, "cross": 1.0, "cross_balance": 0.3}), a)
    mix = eff.illumination(st, LampRig({**vals, "cross": 0.3, "cross_balance": 0.3}), a)
    np.testing.assert_allclose(mix, 0.7 * pair + 0.3 * cross, rtol=1e-5, atol=1e-7)
    assert np.abs(cross - pair).max() > 0.1 * pair.max()
    other = eff.illumination(st, LampRig({**vals, "cross": 0.0, "cross_y": 0.9, "cross_balance": 1.0}), a)
    np.testing.assert_array_equal(other, pair)


def test_artificial_light_colour_tints_the_lamp_light_and_its_veil(frames, renderer):
    """tint_r / tint_b scale the lamps' light per channel (green is the reference): on the lit panel (I - B) and in
    the veil of open water; with lamps only (fill 0) the panel's red and blue scale by exactly the tint."""
    cam = renderer.camera
    T, rr = frames["mid"]
    lamp = {"offset_x": 0.3, "balance": 0.5, "half_angle": 1.2, "fill": 0.0, "veil": 0.05, "power": 0.3}
    white = UnderwaterModel(P, {"artificial_light": lamp}).degrade(rr, cam)
    warm = UnderwaterModel(P, {"artificial_light": {**lamp, "tint_r": 1.3, "tint_b": 0.7}}).degrade(rr, cam)
    hit = np.isfinite(rr.range)
    tr = np.exp(-np.asarray(P.a)[None, None] * rr.range[..., None]) * np.exp(-(P.rho_f * rr.depth) ** 2)[..., None]
    Bk = np.asarray(P.b) * (1 - tr)
    veil0 = white - UnderwaterModel(P, {"artificial_light": {**lamp, "veil": 0.0}}).degrade(rr, cam)
    veil1 = warm - UnderwaterModel(P, {"artificial_light": {**lamp, "veil": 0.0, "tint_r": 1.3,
                                                             "tint_b": 0.7}}).degrade(rr, cam)
    lit = hit & ((white - Bk - veil0).min(-1) > 1e-3)
    assert lit.sum() > 100
    ratio = (warm - Bk - veil1)[lit].sum(0) / (white - Bk - veil0)[lit].sum(0)
    np.testing.assert_allclose(ratio, [1.3, 1.0, 0.7], rtol=1e-3)
    water = ~hit
    np.testing.assert_allclose(veil1[water].sum(0) / veil0[water].sum(0), [1.3, 1.0, 0.7], rtol=1e-3)


def test_artificial_light_veil_on_lamp_side(frames, renderer):
    cam = renderer.camera
    spec = {"artificial_light": {"offset_x": 0.6, "balance": 0.0, "fill": 0.5, "veil": 0.05, "toe_in": 0.2}}
    T, rr = frames["far"]
    diff = degrade(spec, frames["far"], cam) - degrade({}, frames["far"], cam)
    water = ~np.isfinite(rr.range)
    assert (diff[water] > 0).all()                                        # additive light in open water
    right = diff[:, 100:][water[:, 100:]].mean()
    left = diff[:, :60][water[:, :60]].mean()
    assert right > 1.2 * left                                             # skewed towards the lamp (+x)


def test_artificial_light_veil_is_no_stronger_than_the_lamps_light_allows(frames, renderer):
    """The veil is light of the same lamps: lamps that light no surface (fill 1) cast none, and a veil beyond
    ``veil_cap`` (pi R0^2 (b p(pi))_max exp(R0 max a) (1 - fill) power) acts as the cap. Below the cap the
    veil is linear in its parameter."""
    from uw_sil.sim.effects.artificial_light import B_P_PI_MAX, R0, veil_cap

    cam = renderer.camera
    lamp = {"offset_x": 0.6, "balance": 0.0, "toe_in": 0.2, "power": 0.5}
    a = P.a
    water = ~np.isfinite(frames["far"][1].range)
    base = degrade({}, frames["far"], cam)

    def veil(fill, v):
        return (degrade({"artificial_light": {**lamp, "fill": fill, "veil": v}}, frames["far"], cam) - base)[water]

    assert get_effect("artificial_light").is_identity({**lamp, "fill": 1.0, "veil": 0.3})
    np.testing.assert_array_equal(veil(1.0, 0.3), 0.0)
    cap = veil_cap({**lamp, "fill": 0.9}, a)
    assert cap == pytest.approx(math.pi * R0 ** 2 * B_P_PI_MAX * math.exp(R0 * max(a)) * 0.1 * 0.5)
    np.testing.assert_allclose(veil(0.9, 0.5), veil(0.9, cap), rtol=1e-6)          # 0.5 acts as the cap
    small = veil(0.9, cap / 4)
    assert small.max() > 0
    np.testing.assert_allclose(veil(0.9, cap / 2), 2 * small, rtol=1e-4, atol=1e-7)   # linear below it


def test_artificial_light_cache_returns_what_it_computes(frames, renderer):
    """The lamp light's shape is kept per render for the parameter sets that only scale it (power, fill, veil,
    the base model's b and fog): a forward-difference batch, then the same sets in reverse order (all from the
    cache), equal what the evaluator computes without a cache, and the cache stays bounded."""
    T, rr = frames["mid"]
    lamp = EFFECTS["artificial_light"]
    m = UnderwaterModel(P, {"artificial_light": "strong"})
    x = np.concatenate([P.as_vector(), m.effect_vector()])
    X = x[None] + np.diag(2e-3 * np.maximum(1.0, np.abs(x)))
    X = np.concatenate([x[None], X, X[::-1]])
    pm = m.prepare(rr, renderer.camera, pose=T)
    cached = pm(X[:, :7], X[:, 7:])
    st = pm._base_prep.state["artificial_light"]
    assert 0 < len(st["_E"]) <= lamp.cache_entries and 0 < len(st["_V"]) <= lamp.cache_entries
    lamp.cache_entries = 0
    try:
        plain = m.prepare(rr, renderer.camera, pose=T)(X[:, :7], X[:, 7:])
    finally:
        del lamp.cache_entries
    assert np.array_equal(cached, plain)
    assert np.array_equal(cached[1:len(x) + 1], cached[len(x) + 1:][::-1])
    assert not np.array_equal(cached[0], cached[1 + len(x) - 1])        # the veil column moved the image


def test_the_image_before_the_camera_noise_is_reused_bit_for_bit(frames, renderer):
    """Candidates that differ only in the camera noise (the noise plug-in's fit) reuse the image computed
    before it: a batch of noise parameter sets, with lamps, forward scatter and vignetting before the noise and
    compression after it, equals each set evaluated alone by a fresh evaluator, and a change of the earlier
    parameters is not served from the reuse."""
    T, rr = frames["mid"]
    m = UnderwaterModel(P, {"artificial_light": "strong", "forward_scatter": "strong", "vignetting": "strong",
                            "sensor_noise": "strong", "compression": "strong"})
    x = np.concatenate([P.as_vector(), m.effect_vector()])
    names = m.effect_param_names()
    X = np.repeat(x[None], 5, axis=0)
    for j, (n, v) in enumerate([("shot", 0.1), ("read", 1.0), ("corr", 0.3), ("read", 4.0)], start=1):
        X[j, 7 + names.index(f"sensor_noise.{n}")] = v
    X = np.concatenate([X, X[:1]])
    X[-1, 7 + names.index("artificial_light.power")] *= 0.5          # an earlier parameter: no reuse
    pm = m.prepare(rr, renderer.camera, pose=T, seed=3)
    computed = []
    real_terms = pm._terms
    pm._terms = lambda *a, **k: computed.append(1) or real_terms(*a, **k)
    batch = pm(X[:, :7], X[:, 7:])
    assert len(computed) == 2                       # the first set and the one with other lamps
    for k in range(len(X)):
        alone = m.prepare(rr, renderer.camera, pose=T, seed=3)(X[k, :7], X[k, 7:])
        assert np.array_equal(batch[k], alone), k
    assert not np.array_equal(batch[1], batch[2])
    assert not np.array_equal(batch[0], batch[-1])


def _hf_energy(img, mask):
    import cv2
    lap = cv2.Laplacian(img.mean(-1).astype(np.float32), cv2.CV_32F)
    return float((lap[mask] ** 2).mean())


def test_forward_scatter_loses_more_high_frequencies_at_range(frames, renderer):
    cam = renderer.camera
    spec = {"forward_scatter": {"strength": 0.3, "width": 10.0, "tail": 0.3}}
    kept = {}
    for key in ("near", "far"):
        T, rr = frames[key]
        inner = np.isfinite(rr.range)
        import cv2
        inner = cv2.erode(inner.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        kept[key] = _hf_energy(degrade(spec, frames[key], cam), inner) / _hf_energy(degrade({}, frames[key], cam), inner)
    assert kept["near"] < 1 and kept["far"] < kept["near"]


@pytest.mark.parametrize("width", [5.0, 20.0, 40.0])
def test_forward_scatters_halo_is_jaffes_filter(width):
    """With all light forward-scattered and all of it in the halo (tail 1), a bright square at one range is spread by
    Jaffe's ``F^-1{exp(-B R f)}`` (``B R = 2 pi w``): within 5 % of the peak of the exact filter, applied in the
    frequency domain to the mirrored image, everywhere (the levels are octaves apart), the total light kept, and
    the halo as far out as the filter puts it (a Gaussian of that width leaves nothing 10 widths out)."""
    fs = get_effect("forward_scatter")
    h, w, fx = 240, 320, 300.0
    img = np.full((h, w), 0.05, np.float32)
    img[100:140, 140:180] = 1.0
    img[60:70, 40:60] = 0.5
    r = np.full((h, w), 2.0, np.float32)
    terms = SimpleNamespace(state={fs.name: (r, fx)}, D=np.stack([img, 0.5 * img, 0.2 * img]))
    fs.apply(terms, {"strength": 50.0, "width": width, "tail": 1.0}, None)
    scale = fx * width * 1e-3 * 2.0                                          # px
    pad = 3 * max(h, w)
    big = np.pad(img.astype(np.float64), pad, mode="symmetric")
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(big.shape[0]), np.fft.fftfreq(big.shape[1]), indexing="ij"))
    exact = np.real(np.fft.ifft2(np.fft.fft2(big) * np.exp(-2 * np.pi * scale * f)))[pad:pad + h, pad:pad + w]
    got = terms.D[0]
    assert np.abs(got - exact).max() < 0.05 * exact.max()
    np.testing.assert_allclose(terms.D[2], 0.2 * got, rtol=1e-4, atol=1e-6)
    assert abs(float(got.mean() - img.mean())) < 1e-3 * float(img.mean())
    # the halo 10 widths (or 100 px) right of the square: the filter's and ours, well above the background's 0.05
    x = min(179 + int(10 * scale), w - 1)
    halo = exact[120, x] - 0.05
    assert halo > 1e-3
    assert abs((got[120, x] - 0.05) - halo) < 0.25 * halo
    gauss = SimpleNamespace(state=terms.state, D=np.stack([img, 0.5 * img, 0.2 * img]))
    fs.apply(gauss, {"strength": 50.0, "width": width, "tail": 0.0}, None)
    assert gauss.D[0][120, x] - 0.05 < 0.1 * halo


def test_marine_snow_sparse_positive_new_every_frame(frames, renderer):
    cam = renderer.camera
    spec = {"marine_snow": "strong"}
    base = degrade({}, frames["mid"], cam)
    a = degrade(spec, frames["mid"], cam, seed=1)
    b = degrade(spec, frames["mid"], cam, seed=2)
    a2 = degrade(spec, frames["mid"], cam, seed=1)
    np.testing.assert_array_equal(a, a2)                                  # reproducible with a seed
    d = a - base
    assert d.min() >= -1e-6                                               # bright particles only
    changed = (d.max(-1) > 10 / 255).mean()
    assert 0 < changed < 0.05                                             # sparse
    assert not np.array_equal(a, b)                                       # new particles every frame


def test_marine_snow_defocus_spreads_the_near_particles_light(monkeypatch):
    """A lens focused at 2 m images a particle at 0.2 m as a disc of fx * A * |1/z - 1/focus| px: with an aperture the
    near particles' light is spread (fainter peaks, the same light), a particle at the focus stays sharp, and
    aperture 0 is the pinhole of before, bit for bit."""
    import uw_sil.sim.effects.marine_snow as ms

    cam = CameraModel.from_fov(320, 240)
    h, w = 240, 320

    def snow(z, values, seed=5):
        depth = np.full((h, w), np.inf, np.float32)
        terms = SimpleNamespace(camera=cam, shape=(h, w), geom=SimpleNamespace(depth=depth), lamps=None,
                                a=np.array([0.3, 0.1, 0.08], np.float32))
        monkeypatch.setattr(ms, "Z_MIN", z)
        monkeypatch.setattr(ms, "Z_MAX", 1.1 * z)         # every particle within 10 % of depth z
        snow = get_effect("marine_snow")
        return snow.particles(terms, {**snow.defaults(), **values}, np.random.default_rng(seed))

    sharp = {"density": 3e5, "brightness": 1.0, "size": 0.5}
    lens = dict(sharp, aperture=10.0, focus=2.0)
    near0, near = snow(0.2, sharp), snow(0.2, lens)
    disc = cam.fx * 10e-3 * (1 / 0.2 - 1 / 2.0)         # 10 px at 320 px wide
    assert disc > 8
    inner = (slice(None), slice(40, -40), slice(40, -40))
    assert abs(near[inner].sum() / near0[inner].sum() - 1) < 0.05            # the light is conserved
    assert near.max() < 0.25 * near0.max()                                   # spread over the disc
    np.testing.assert_array_equal(snow(2.0, lens), snow(2.0, sharp))          # in focus: as sharp as before
    np.testing.assert_array_equal(snow(0.2, dict(sharp, aperture=0.0)), near0)


def test_sensor_noise_signal_dependent_and_fixed_pattern(frames, renderer):
    cam = renderer.camera
    grey = UnderwaterParams(a=(0.0, 0.0, 0.0), b=(0.5, 0.5, 0.5), rho_f=0.0)
    T, rr = frames["near"]
    spec = {"sensor_noise": {"shot": 1.0, "read": 1.0, "corr": 0.0, "fpn": 0.0}}
    base = degrade({}, frames["near"], cam, params=grey)
    noise = degrade(spec, frames["near"], cam, seed=3, params=grey) - base
    lum = base.mean(-1)
    dark, bright = lum < 0.2, lum > 0.6
    assert dark.sum() > 50 and bright.sum() > 50
    assert noise[bright].std() > 1.5 * noise[dark].std()                  # variance grows with intensity
    fpn = {"sensor_noise": {"shot": 0.0, "read": 0.0, "fpn": 0.02}}
    np.testing.assert_array_equal(degrade(fpn, frames["near"], cam, seed=1),
                                  degrade(fpn, frames["near"], cam, seed=2))   # fixed pattern: same every frame
    assert not np.array_equal(degrade(spec, frames["near"], cam, seed=1), degrade(spec, frames["near"], cam, seed=2))


def test_sensor_noise_column_and_row_patterns_are_fixed_offsets(frames, renderer):
    cam = renderer.camera
    grey = UnderwaterParams(a=(0.0, 0.0, 0.0), b=(0.5, 0.5, 0.5), rho_f=0.0)
    base = degrade({}, frames["near"], cam, params=grey)
    col = degrade({"sensor_noise": {"col": 2.0}}, frames["near"], cam, seed=1, params=grey) - base
    # one offset per column, the same down the column and in all channels (up to the 8-bit rounding),
    # about 2 DN std over columns
    q, ok = 1.01 / 255, (base > 8 / 255) & (base < 247 / 255)          # not clipped
    np.testing.assert_allclose(col[ok], np.broadcast_to(np.median(col, axis=(0, 2), keepdims=True), col.shape)[ok],
                               atol=q)
    assert 1.6 < 255 * np.median(col, axis=(0, 2)).std() < 2.4
    row = degrade({"sensor_noise": {"row": 1.0}}, frames["near"], cam, seed=2, params=grey) - base
    np.testing.assert_allclose(row[ok], np.broadcast_to(np.median(row, axis=(1, 2), keepdims=True), row.shape)[ok],
                               atol=q)
    assert 0.7 < 255 * np.median(row, axis=(1, 2)).std() < 1.3
    both = {"sensor_noise": {"read": 1.0, "col": 2.0}}
    d = degrade(both, frames["near"], cam, seed=1, params=grey) - degrade(both, frames["near"], cam, seed=2, params=grey)
    # the pattern cancels between two frames: their difference has no column structure left
    assert np.median(d, axis=(0, 2)).std() < 0.25 * np.median(col, axis=(0, 2)).std()


def test_remembered_white_noise_is_the_draw_and_leaves_the_generator_where_the_draw_would():
    """The sensor-noise field is remembered by generator state within a fit (it draws from the same seed for
    every candidate): the remembered field must be the draw itself, the generator must end where drawing would
    have left it, and a different state must draw anew; outside a fit nothing is kept."""
    import uw_sil.sim.effects.sensor_noise as sn
    from uw_sil.sim.effects.base import remembered_draws

    shape = (3, 40, 50)
    fresh = np.random.default_rng(7)
    want = fresh.standard_normal(shape, dtype=np.float32)
    want_next = fresh.random()
    with remembered_draws():
        for _ in range(2):                                # the second time from the memory
            g = np.random.default_rng(7)
            np.testing.assert_array_equal(sn.white_normal(g, shape), want)
            assert g.random() == want_next
        assert len(sn._white) == 1
        g = np.random.default_rng(7)
        g.random()
        assert not np.array_equal(sn.white_normal(g, shape), want)
        assert not sn.white_normal(np.random.default_rng(7), shape).flags.writeable
        # correlated: the memory's field is not written over (the same noise twice)
        a = sn.correlated_normal(np.random.default_rng(9), shape, 0.8)
        np.testing.assert_array_equal(sn.correlated_normal(np.random.default_rng(9), shape, 0.8), a)
        assert 0.8 < a.std() < 1.2
    assert not sn._white                                  # forgotten after the fit
    g = np.random.default_rng(7)
    np.testing.assert_array_equal(sn.white_normal(g, shape), want)
    assert g.random() == want_next and not sn._white      # a live camera's frames are not kept


def test_remembered_particles_are_the_draws(frames, renderer, monkeypatch):
    """Within a fit (``remembered_draws``) the particles' places and the light on them are remembered by generator
    state, density and scene: snow of other sizes and brightness from the same seed must be the image drawn
    afresh, under the lamps and without; another scene's depth is lit anew, and nothing is kept after the fit."""
    import uw_sil.sim.effects.marine_snow as ms
    from uw_sil.sim.effects.base import remembered_draws
    from uw_sil.sim.model import Geometry

    cam = renderer.camera
    specs = [{"marine_snow": {"density": 400.0, "brightness": b, "size": z}} for b, z in ((1.0, 3.0), (0.5, 1.0),
                                                                                        (2.0, 6.0))]
    specs += [{**s, "artificial_light": {"fill": 0.3, "offset_x": 0.4}} for s in specs[:2]]
    geoms = {f: Geometry.from_render(frames[f][1], cam, frames[f][0]) for f in ("near", "far")}

    def snow(i, f, seed=4):
        return UnderwaterModel(P, specs[i]).degrade(geoms[f], cam, rng=np.random.default_rng(seed), pose=frames[f][0])

    want = {(i, f): snow(i, f) for i in range(len(specs)) for f in geoms}
    lit = []
    real_lit = ms._lit
    monkeypatch.setattr(ms, "_lit", lambda *a: lit.append(1) or real_lit(*a))
    with remembered_draws():
        for _ in range(2):
            for (i, f), w in want.items():
                np.testing.assert_array_equal(snow(i, f), w)
        assert not np.array_equal(snow(0, "near", seed=5), want[0, "near"])     # another seed: other particles
        assert len(ms._placed) > 0
    # lit once per scene and light (two frames, with and without lamps) and for the other seed: not per candidate
    assert len(lit) == 5, len(lit)
    assert len(ms._placed) == 0
    assert (want[0, "near"] > want[1, "near"]).any()                    # the sizes and brightness did change them


def test_camera_response_is_a_function_of_intensity(frames, renderer):
    cam = renderer.camera
    base = degrade({}, frames["near"], cam)
    img = degrade({"camera_response": "strong"}, frames["near"], cam)
    v = EFFECTS["camera_response"].severity("strong")
    g = np.array([v["gain_r"], v["gain_g"], v["gain_b"]])
    expect = v["black"] + (1 - v["black"]) * np.clip(base * g, 0, 1) ** (1 / v["gamma"])
    np.testing.assert_allclose(img, expect, atol=2e-6)


@pytest.mark.parametrize("p,toe,offset,slope", [(0.45, 0.018, 0.099, 4.5),             # ITU-R BT.709 OETF
                                                (1 / 2.4, 0.0031308, 0.055, 12.92)])     # IEC 61966-2-1 sRGB
def test_camera_response_toe_is_the_standards_linear_segment(p, toe, offset, slope):
    # the standards' published offset and slope follow from the break and the exponent alone (value and
    # slope continuous; sRGB's published 12.92 is 1.6 % off its own slope-continuous 12.71), and the tone
    # curve is theirs on either side of the break
    cr = EFFECTS["camera_response"]
    values = {**cr.defaults(), "gamma": 1 / p, "toe": toe}
    _, _, o, s = cr.curve(values)
    assert o == pytest.approx(offset, abs=0.001) and s == pytest.approx(slope, rel=0.02)
    x = np.linspace(0, 1, 20001, dtype=np.float32)
    terms = SimpleNamespace(I=np.stack([x, x, x]).copy())
    cr.apply(terms, values, None)
    standard = np.where(x < toe, slope * x, (1 + offset) * x.astype(float) ** p - offset)
    assert np.abs(terms.I[1] - standard).max() < 0.002                 # half a grey level of 8 bits
    assert (np.diff(terms.I[1]) >= 0).all()                            # monotone through the break
    np.testing.assert_allclose(cr.invert(terms.I, None, values)[1], x, atol=2e-6)
    plain = SimpleNamespace(I=np.stack([x, x, x]).copy())
    cr.apply(plain, {**values, "toe": 0.0}, None)                     # the pure power law differs in the dark
    assert np.abs(plain.I[1] - standard)[x < 0.1].max() > 0.02


def test_backscatter_coefficient_changes_objects_not_water(frames, renderer):
    cam = renderer.camera
    T, rr = frames["mid"]
    d = degrade({"backscatter_coefficient": "strong"}, frames["mid"], cam) - degrade({}, frames["mid"], cam)
    water = ~np.isfinite(rr.range)
    assert np.abs(d[water]).max() == 0
    assert np.abs(d[~water]).mean() > 0.005


def test_pose_error_shifts_the_image(frames, renderer):
    cam = renderer.camera
    T, rr = frames["mid"]
    assert np.array_equal(degrade({"pose_error": {}}, frames["mid"], cam), degrade({}, frames["mid"], cam))
    tx = 0.05
    model = UnderwaterModel(P, {"pose_error": {"tx": tx}})
    pm = model.prepare(rr, cam, pose=T)
    terms, _, prep = pm._terms(P.as_vector(), model.effect_vector(), seed=None, restoring=True)
    hit0, hit1 = np.isfinite(rr.range), prep.geom.hit
    u0 = np.nonzero(hit0)[1].mean()
    u1 = np.nonzero(hit1)[1].mean()
    expect = cam.fx * tx / np.median(rr.depth[hit0])                      # points move by +t in the camera
    assert abs((u1 - u0) - expect) < 0.6
    Dm = np.eye(4)
    Dm[0, 3] = tx
    truth = renderer.render(Dm @ T)                                      # rendered at the true pose
    assert (hit1 != np.isfinite(truth.range)).mean() < 0.3 * (hit0 != np.isfinite(truth.range)).mean()
    np.testing.assert_allclose(prep.geom.pose, np.block([[np.eye(3), np.array([[tx], [0], [0]])], [0, 0, 0, 1]]) @ T)


def test_unmodeled_geometry_adds_a_floor_below(frames, renderer):
    cam = renderer.camera
    T, rr = frames["far"]
    model = UnderwaterModel(P, {"unmodeled_geometry": "strong"})
    pm = model.prepare(rr, cam, pose=T)
    terms, _, prep = pm._terms(P.as_vector(), model.effect_vector(), seed=None, restoring=True)
    floor = prep.geom.labels == 2
    rows = np.nonzero(floor)[0]
    assert floor.mean() > 0.1 and rows.min() > cam.cy                     # below the horizon of a level camera
    assert (prep.geom.labels[np.isfinite(rr.range)] == 1).all()           # the panel stays in front
    with pytest.raises(ValueError, match="pose"):
        model.degrade(rr, cam)


def test_a_seafloor_that_changes_only_its_colour_reuses_its_shape_and_texture_samples(frames, renderer, monkeypatch):
    """A forward-difference batch of a seafloor model (a least-squares Jacobian): the albedo's and the contrast's
    columns reuse the floor the unchanged height and tilt made (no new intersection or texture sampling), and
    every candidate equals itself evaluated alone by a fresh evaluator of a fresh view, bit for bit."""
    from uw_sil.sim.effects.unmodeled_geometry import UnmodeledGeometry

    T, rr = frames["far"]
    model = UnderwaterModel(P, {"unmodeled_geometry": {"floor_y": -0.9, "tilt": 0.05, "albedo": 0.8,
                                                       "contrast": 0.7}})
    x = np.concatenate([P.as_vector(), model.effect_vector()])
    X = np.concatenate([x[None], x[None] + np.diag(2e-3 * np.maximum(1.0, np.abs(x)))])
    made = []
    real = UnmodeledGeometry._floor
    monkeypatch.setattr(UnmodeledGeometry, "_floor", staticmethod(lambda *a: made.append(a[1:3]) or real(*a)))
    batch = model.prepare(rr, renderer.camera, pose=T)(X[:, :7], X[:, 7:])
    assert made == [(X[k, 7], X[k, 8]) for k in (0, 8, 9)]     # the centre, the height's column, the tilt's
    monkeypatch.setattr(UnmodeledGeometry, "_floor", staticmethod(real))
    for k in range(len(X)):
        alone = model.prepare(renderer.render(T), renderer.camera, pose=T)(X[k, :7], X[k, 7:])
        assert np.array_equal(batch[k], alone), k
    assert len({batch[k].tobytes() for k in (0, 10, 11)}) == 3                # albedo and contrast change it


def test_the_seafloor_texture_pyramid_is_built_once_when_threads_ask_for_it_together(monkeypatch):
    """The first seafloor simulations of a process can run on several threads (θ of a candidate batch). Each
    thread that found the mip pyramid unbuilt appended its own levels to the module's list: 14 levels instead
    of 7, the wrong level for every pixel footprint from then on, and a diagnosis refitted the seafloor to
    other values on two threads than on one (held-out evidence and confidences moved with the core count).
    Here every thread is held inside the texture's construction until the others have arrived there too (or
    0.5 s have passed: with the build under a lock, they cannot arrive), so the unguarded build fails every
    time; each thread must get the same complete pyramid."""
    import threading

    import uw_sil.sim.effects.unmodeled_geometry as ug
    import uw_sil.sim.scene as scene

    real = scene.seafloor_texture
    inside = threading.Barrier(4, timeout=0.5)

    def slow_texture(*a, **k):
        try:
            inside.wait()
        except threading.BrokenBarrierError:
            pass
        return real(*a, **k)

    monkeypatch.setattr(scene, "seafloor_texture", slow_texture)
    monkeypatch.setattr(ug, "_mips", type(ug._mips)())
    start = threading.Barrier(4)
    got = [None] * 4

    def ask(i):
        start.wait()
        got[i] = ug._texture_mips()

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    sizes = [[m.shape[0] for m in g] for g in got]
    assert sizes[0] == [ug.TEX_SIZE // 2 ** L + 2 for L in range(7)], sizes[0]
    assert all(s == sizes[0] for s in sizes), sizes
    assert all(g is got[0] for g in got)
    assert len(ug._texture_mips()) == 7


@pytest.mark.parametrize("name", sorted(NAMES))
def test_mild_subtle_strong_stronger(name, frames, renderer):
    cam = renderer.camera
    base = degrade({}, frames["mid"], cam)
    mild = np.abs(degrade({name: "mild"}, frames["mid"], cam, seed=4) - base).mean()
    strong = np.abs(degrade({name: "strong"}, frames["mid"], cam, seed=4) - base).mean()
    assert 0 < mild < strong


# ---------------------------------------------------------------------------- synthetic trials


def test_synth_injects_effects_recorded_only_in_truth(tmp_path, capsys):
    import json

    from uw_sil.bags import read_samples
    from uw_sil.cli import build_parser, main

    help_text = " ".join(a.help or "" for a in build_parser()._subparsers._group_actions[0].choices["synth"]._actions)
    assert all(name in help_text for name in NAMES)
    common = ["--frames", "2", "--width", "160", "--height", "120", "--seed", "3"]
    assert main(["synth", "--out", str(tmp_path / "a.mcap"), *common]) == 0
    assert main(["synth", "--out", str(tmp_path / "b.mcap"), *common,
                 "--effects", "vignetting=strong,marine_snow=mild,marine_snow.density=200"]) == 0
    truth = json.loads((tmp_path / "b.truth.json").read_text())
    assert truth["effects"] == ["marine_snow", "vignetting"]
    assert truth["effect_params"]["vignetting"] == EFFECTS["vignetting"].severity("strong")
    assert truth["effect_params"]["marine_snow"]["density"] == 200
    assert json.loads((tmp_path / "a.truth.json").read_text())["effects"] == []
    a = list(read_samples(tmp_path / "a.mcap"))
    b = list(read_samples(tmp_path / "b.mcap"))
    assert len(a) == len(b) == 2
    np.testing.assert_array_equal(a[0].pose, b[0].pose)
    ia, ib = a[0].image.astype(float), b[0].image.astype(float)
    assert ib[0, 0].sum() < ia[0, 0].sum() - 20                          # vignetted corner
    meta = (tmp_path / "b" / "metadata.yaml").read_text()
    assert "vignetting" not in meta and "marine_snow" not in meta        # nothing of it in the bag
    capsys.readouterr()
    assert main(["synth", "--out", str(tmp_path / "c.mcap"), *common, "--effects", "vignetting,fog_of_war"]) == 2
    assert "fog_of_war" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


# ---------------------------------------------------------------------------- params YAML and sim_camera


def test_params_yaml_carries_effects(tmp_path):
    import yaml

    from uw_sil.fit.backward import read_params_yaml, write_params_yaml

    effects = parse_effects("artificial_light=mild,vignetting=strong")
    path = write_params_yaml(tmp_path / "fit.yaml", P, fog="exp", noise_sigma=1.5, effects=effects)
    ros = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
    assert ros["effects"] == "artificial_light,vignetting" and ros["vignetting.k1"] == effects["vignetting"]["k1"]
    back = read_params_yaml(path)
    assert back["params"] == P and back["fog"] == "exp" and back["noise_sigma"] == 1.5
    assert back["effects"] == effects
    # nested form, a listed preset without values, and no effects at all
    nested = {"sim_camera": {"ros__parameters": {**P.as_dict(), "effects": "vignetting,marine_snow=mild",
                                                 "vignetting": {"k1": -0.3}}}}
    (tmp_path / "n.yaml").write_text(yaml.safe_dump(nested))
    got = read_params_yaml(tmp_path / "n.yaml")["effects"]
    assert got["vignetting"]["k1"] == -0.3 and got["marine_snow"] == EFFECTS["marine_snow"].severity("mild")
    write_params_yaml(tmp_path / "p.yaml", P)
    assert read_params_yaml(tmp_path / "p.yaml")["effects"] == {}
    nested["sim_camera"]["ros__parameters"]["vignetting"]["k7"] = 1.0
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(nested))
    with pytest.raises(ValueError, match="k7"):
        read_params_yaml(tmp_path / "bad.yaml")


def test_sim_camera_node_declares_effect_parameters(tmp_path, frames):
    rclpy = pytest.importorskip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from rosproc import domain_id
    from uw_sil.fit.backward import write_params_yaml
    from uw_sil.nodes.sim_camera import SimCameraNode

    effects = parse_effects("artificial_light=mild,vignetting=strong")
    path = write_params_yaml(tmp_path / "fit.yaml", P, effects=effects)
    ctx = Context()
    rclpy.init(context=ctx, args=["--ros-args", "--params-file", str(path)], domain_id=domain_id())
    node = None
    try:
        node = SimCameraNode(context=ctx, parameter_overrides=[Parameter("width", value=160),
                                                               Parameter("height", value=120)])
        assert node.sim.effects == effects                                # flat dotted names from the file
        d = node.describe_parameter("artificial_light.offset_x")
        assert d.read_only is False and d.floating_point_range[0].from_value == -1.5
        assert node.describe_parameter("effects").read_only
        assert not node.has_parameter("marine_snow.density")              # only listed effects
        r = node.set_parameters([Parameter("vignetting.k1", value=-0.1)])[0]
        assert r.successful and node.sim.effects["vignetting"]["k1"] == -0.1
        r = node.set_parameters([Parameter("vignetting.k2", value=5.0)])[0]
        assert not r.successful and node.sim.effects["vignetting"]["k2"] == effects["vignetting"]["k2"]
        T, rr = frames["mid"]
        want = UnderwaterModel(P, {**effects, "vignetting": {**effects["vignetting"], "k1": -0.1}})
        np.testing.assert_array_equal(node.sim.render(T).image, want.degrade(rr, node.sim.camera, pose=T))
    finally:
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()


def test_prepared_model_takes_pixel_coverage_where_the_scene_stays(frames, renderer):
    """Area-exact silhouettes of a reduced render (``cover``) scale the transmission of the scene's own
    pixels: without geometry effects, with a seafloor (it only fills water), never with a pose error (the
    silhouettes move; a coverage at the identity alone would make the objective jump there)."""
    cam = renderer.camera
    T, rr = frames["far"]
    hit = np.isfinite(rr.range)
    cover = np.where(hit, 0.5, 0.0).astype(np.float32)
    base, ev0 = P.as_vector(), np.zeros(0)
    full = UnderwaterModel(P).prepare(rr, cam, pose=T)(base, ev0)
    half = UnderwaterModel(P).prepare(rr, cam, pose=T, cover=cover)(base, ev0)
    b = np.asarray(P.b, np.float32)
    # I = i T + b (1 - T): halving T moves the panel pixels half way towards the background colour
    np.testing.assert_allclose(half[hit] - b, 0.5 * (full[hit] - b), atol=2e-6)
    np.testing.assert_array_equal(half[~hit], full[~hit])
    floor = UnderwaterModel(P, {"unmodeled_geometry": "strong"})
    pm = floor.prepare(rr, cam, pose=T, cover=cover)
    _, _, prep = pm._terms(base, floor.effect_vector(), seed=0)
    assert (prep.mask[hit] == 0.5).all() and (prep.mask[prep.geom.hit & ~hit] == 1).all()
    pose = UnderwaterModel(P, {"pose_error": {"tx": 0.0}})
    assert pose.prepare(rr, cam, pose=T, cover=cover).cover is None
    with pytest.raises(ValueError, match="cover has shape"):
        UnderwaterModel(P).prepare(rr, cam, pose=T, cover=cover[1:])
