"""The compression effect: a float JPEG round trip that agrees with libjpeg, its blocking, identity and padding,
and its place in the underwater model (last of the sensor stage)."""
import io
import os

import cv2
import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from datapaths import TEST_DATA
from uw_sil.sim.camera import CameraModel
from uw_sil.sim.effects import EFFECTS
from uw_sil.sim.effects.compression import CHROMA_TABLE, LUMA_TABLE, jpeg_roundtrip, quant_tables
from uw_sil.sim.model import UnderwaterModel
from uw_sil.sim.params import UnderwaterParams
from uw_sil.sim.scene import facing_pose

NATURAL = TEST_DATA / "real_underwater" / "suim_test" / "images" / "f_r_1965_.jpg"   # 640x480, PROVENANCE.md
P = UnderwaterParams(a=(0.35, 0.1, 0.08), b=(0.06, 0.3, 0.4), rho_f=0.05)


@pytest.fixture(scope="module")
def natural_bgr():
    bgr = cv2.imread(str(NATURAL), cv2.IMREAD_COLOR)
    assert bgr is not None and bgr.shape == (480, 640, 3)
    return bgr


def psnr(a, b):
    return 10 * np.log10(255.0 ** 2 / np.mean((np.asarray(a, float) - np.asarray(b, float)) ** 2))


def luma_blockiness(rgb):
    """Mean |difference| of neighbouring luma samples across 8x8 block boundaries over the mean within blocks
    (horizontal and vertical neighbours): about 1 for an image without blocking, above 1 with it."""
    y = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    dx, dy = np.abs(np.diff(y, axis=1)), np.abs(np.diff(y, axis=0))
    bx, by = np.arange(dx.shape[1]) % 8 == 7, np.arange(dy.shape[0]) % 8 == 7
    across = np.concatenate([dx[:, bx].ravel(), dy[by].ravel()]).mean()
    within = np.concatenate([dx[:, ~bx].ravel(), dy[~by].ravel()]).mean()
    return across / within


# ---------------------------------------------------------------------------- against libjpeg


def test_quantization_tables_are_libjpegs():
    """The tables libjpeg (through Pillow and OpenCV) writes into the file, at qualities on both branches of
    the IJG scaling (37: integer division 5000 // 37 = 135)."""
    from PIL import Image

    qy, qc = quant_tables(50)
    np.testing.assert_array_equal(qy, LUMA_TABLE)
    np.testing.assert_array_equal(qc, CHROMA_TABLE)
    assert (quant_tables(100)[0] == 1).all() and (quant_tables(1)[1] == 255).all()
    img = np.zeros((16, 16, 3), np.uint8)
    for q in (10, 37, 75, 95):
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, q])
        assert ok
        tables = Image.open(io.BytesIO(buf.tobytes())).quantization      # natural (row-major) order
        qy, qc = quant_tables(q)
        np.testing.assert_array_equal(np.reshape(tables[0], (8, 8)), qy, err_msg=f"luma q={q}")
        np.testing.assert_array_equal(np.reshape(tables[1], (8, 8)), qc, err_msg=f"chroma q={q}")
    for bad in (0.5, 101, float("nan")):
        with pytest.raises(ValueError, match="quality"):
            quant_tables(bad)


@pytest.mark.parametrize("subsample", [True, False], ids=["420", "444"])
@pytest.mark.parametrize("quality", [50, 75, 95])
def test_roundtrip_agrees_with_opencv_jpeg(natural_bgr, quality, subsample):
    """Float round trip vs OpenCV's libjpeg (integer DCT, fixed-point colour, 8-bit output) on the 640x480 SUIM
    image. Measured when this was written (OpenCV 4.14): mean |difference| 1.31 / 0.49 / 0.35 DN at q 50 /
    75 / 95 with 4:2:0 (1.23 / 0.49 / 0.34 at 4:4:4), PSNR between the two 42.2 / 51.7 / 53.9 dB (42.6 / 51.4
    / 54.0); each is 3.8-6.5 dB closer to libjpeg's result than the uncompressed image is. The source is
    itself a JPEG, which is why q 50 (near its own quality) sits on more rounding ties than q 75. Limits with
    margin: mean |difference| < 1.6 DN, PSNR > 40 dB, and at least 2.5 dB closer than the uncompressed
    image."""
    flag = cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420 if subsample else cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444
    ok, buf = cv2.imencode(".jpg", natural_bgr, [cv2.IMWRITE_JPEG_QUALITY, quality,
                                                 cv2.IMWRITE_JPEG_SAMPLING_FACTOR, flag])
    assert ok
    ref = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float64)
    rgb = natural_bgr[..., ::-1].astype(np.float64)
    ours = jpeg_roundtrip(rgb / 255.0, quality, subsample=subsample)
    assert ours.dtype == np.float32 and ours.shape == rgb.shape
    ours = ours.astype(np.float64) * 255.0
    mad = np.abs(ours - ref).mean()
    assert mad < 1.6, f"mean |ours - libjpeg| = {mad:.2f} DN"
    assert psnr(ours, ref) > 40.0
    assert psnr(ours, ref) > psnr(rgb, ref) + 2.5


# ---------------------------------------------------------------------------- properties


def test_blocking_rises_as_quality_falls(natural_bgr):
    """Luma differences across the 8x8 grid over those within blocks, on the image resized to 400x296 (which
    moves its own JPEG grid off ours): 0.96 uncompressed; 1.01 / 1.08 / 1.25 / 1.47 / 2.46 at q 95 / 90 / 75
    / 50 / 10 when written."""
    img = cv2.resize(natural_bgr[..., ::-1], (400, 296), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    b0 = luma_blockiness(img)
    assert 0.9 < b0 < 1.02
    b = [luma_blockiness(jpeg_roundtrip(img, q)) for q in (95, 90, 75, 50, 10)]
    assert all(x < y for x, y in zip(b, b[1:])), b
    assert b[0] > b0 and b[-1] > 2.0


def test_defaults_leave_the_image_unchanged_and_presets_do_not():
    e = EFFECTS["compression"]
    assert e.stage == "sensor" and not e.invertible and not e.random_per_frame
    assert e.is_identity(e.defaults())
    assert e.is_identity({"quality": 100.0, "chroma": 0.3})                 # below the 4:2:0 threshold
    assert not e.is_identity({"quality": 100.0, "chroma": 0.5})
    assert not e.is_identity(e.severity("mild")) and not e.is_identity(e.severity("strong"))


def test_padding_and_layouts():
    """Sides that are not multiples of 16: the result has the input's shape and equals the round trip of
    the image padded by edge replication, cropped; planar and interleaved layouts agree."""
    rng = np.random.default_rng(3)
    h, w = 481, 643
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([0.5 + 0.3 * np.sin(xx / 17 + c) * np.cos(yy / 23) for c in range(3)], -1)
    img = np.clip(img + 0.01 * rng.standard_normal(img.shape, dtype=np.float32), 0, 1)
    for subsample, m in ((True, 16), (False, 8)):
        out = jpeg_roundtrip(img, 60, subsample=subsample)
        assert out.shape == (h, w, 3) and out.dtype == np.float32
        assert 0.0 <= out.min() and out.max() <= 1.0
        padded = np.pad(img, ((0, -h % m), (0, -w % m), (0, 0)), mode="edge")
        assert padded.shape[:2] == ((496, 656) if m == 16 else (488, 648))
        np.testing.assert_array_equal(out, jpeg_roundtrip(padded, 60, subsample=subsample)[:h, :w])
        planar = jpeg_roundtrip(np.ascontiguousarray(img.transpose(2, 0, 1)), 60, subsample, channel_axis=0)
        np.testing.assert_allclose(planar.transpose(1, 2, 0), out, atol=1e-6)
        assert 0 < np.abs(out - img).mean() < 0.015                          # 2.5 DN noise on a smooth image
    tiny = jpeg_roundtrip(img[:3, :5], 80)
    assert tiny.shape == (3, 5, 3)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        jpeg_roundtrip(img[..., :2], 80)
    with pytest.raises(ValueError, match="quality"):
        jpeg_roundtrip(img, 0)


def test_deterministic():
    img = np.random.default_rng(0).random((40, 56, 3)).astype(np.float32)
    np.testing.assert_array_equal(jpeg_roundtrip(img, 30), jpeg_roundtrip(img, 30))


# ---------------------------------------------------------------------------- in the model


@pytest.fixture(scope="module")
def frame():
    from uw_sil.sim.render import Renderer

    with Renderer(camera=CameraModel.from_fov(160, 120)) as r:
        T = facing_pose(2.0, yaw=0.1)
        yield T, r.render(T), r.camera


def test_model_compresses_last_in_the_sensor_stage(frame):
    """Through :class:`UnderwaterModel`: the defaults are bit-identical to no effect; a preset is the round
    trip of the frame with the other effects (noise first, then compression); the prepared evaluator takes the
    quality as a parameter."""
    T, rr, cam = frame
    base = UnderwaterModel(P).degrade(rr, cam, pose=T)
    np.testing.assert_array_equal(UnderwaterModel(P, {"compression": {}}).degrade(rr, cam, pose=T), base)
    strong = UnderwaterModel(P, {"compression": "strong"}).degrade(rr, cam, pose=T)
    np.testing.assert_allclose(strong, jpeg_roundtrip(base, 50), atol=1e-6)
    noisy = UnderwaterModel(P, {"sensor_noise": "strong"}).degrade(rr, cam, rng=np.random.default_rng(2), pose=T)
    both = UnderwaterModel(P, {"sensor_noise": "strong", "compression": "mild"}).degrade(
        rr, cam, rng=np.random.default_rng(2), pose=T)
    np.testing.assert_allclose(both, jpeg_roundtrip(noisy, 90), atol=1e-6)
    model = UnderwaterModel(P, {"compression": "mild"})
    pm = model.prepare(rr, cam, pose=T)
    assert pm.param_names == ("compression.quality", "compression.chroma")
    out = pm(np.tile(P.as_vector(), (3, 1)), np.array([[90.0, 1.0], [20.0, 1.0], [100.0, 0.0]]))
    np.testing.assert_allclose(out[0], model.degrade(rr, cam, pose=T), atol=1e-6)
    np.testing.assert_array_equal(out[2], base)
    assert np.abs(out[1] - base).mean() > np.abs(out[0] - base).mean() > 0


def test_simcam_with_compression(frame):
    from uw_sil.sim.simcam import SimCamera

    T, rr, cam = frame
    with SimCamera(P, camera=cam, effects="compression=mild") as sim:
        img = sim.render(T).image
        np.testing.assert_array_equal(img, UnderwaterModel(P, {"compression": "mild"}).degrade(rr, cam, pose=T))
        sim.set_effect_params({"compression.quality": 40})
        assert sim.effects["compression"]["quality"] == 40
        np.testing.assert_allclose(sim.render(T).image, jpeg_roundtrip(UnderwaterModel(P).degrade(rr, cam), 40),
                                   atol=1e-6)
