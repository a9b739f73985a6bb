"""The physically based generator of the concealed-effects bench (bench/physical_effects.py) writes a bag
the project reads: the right number of frames, the camera's size, the recorded poses, and no truth."""
import os
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


@pytest.mark.parametrize("effects", [{}, {"marine_snow": "strong", "sensor_noise": "mild", "vignetting": "strong"}])
def test_physical_bag_is_readable_and_blind(tmp_path, effects):
    from physical_effects import synth_physical

    from uw_sil.bags import open_bag, read_samples

    bag = tmp_path / "trial.mcap"
    truth = synth_physical(bag, effects, n_frames=3, seed=3, width=160, bs_step=16)
    assert truth["effects"] == {"artificial_light": "always", **effects}
    info = open_bag(tmp_path / "trial")
    assert info.topics["/camera/image_raw"].count == 3
    assert not any("truth" in t for t in info.topics)
    files = sorted(p.name for p in (tmp_path / "trial").rglob("*") if p.is_file())
    assert files == ["metadata.yaml", "trial.mcap"]          # nothing next to the bag
    assert not any(tmp_path.glob("*truth*"))
    samples = list(read_samples(tmp_path / "trial"))
    assert len(samples) == 3
    ranges = [float(np.linalg.norm(s.pose[:3, 3])) for s in samples]
    assert np.allclose(ranges, truth["ranges"], atol=1e-6) and ranges[0] > ranges[-1]
    for s in samples:
        assert s.image.shape == (120, 160, 3) and s.image.dtype == np.uint8
        assert s.camera.width == 160 and s.camera.height == 120
    last = samples[-1].image.astype(float)
    assert 5 < last.mean() < 120                                 # dark, lamp-lit footage, not black


def test_unknown_physical_effect_is_refused(tmp_path):
    from physical_effects import synth_physical

    with pytest.raises(ValueError):
        synth_physical(tmp_path / "t.mcap", {"backscatter_coefficient": "mild"}, n_frames=2, width=160)


def test_an_effect_is_measured_alone_on_the_noise_free_dive(tmp_path):
    """``noise=False`` and shared ``draws`` (what bench_physical_dives.py measures an effect's visible energy
    with): the same call gives the same image; without noise it differs from the recording; with the same draws,
    removing vignetting from a snowy dive darkens nothing but the falloff (the particles stay where they were),
    while the default draws of the smaller set move them."""
    from physical_effects import synth_physical

    eff = {"marine_snow": "strong", "vignetting": "strong"}

    def images(effects, **kw):
        tr = synth_physical(tmp_path / "t.mcap", effects, n_frames=2, seed=3, width=160, bs_step=16,
                            return_images=True, **kw)
        return np.stack(tr["_images"]).astype(float)

    clean = images(eff, noise=False)
    assert np.array_equal(clean, images(eff, noise=False))
    assert np.abs(images(eff) - clean).mean() > 0.3                  # photon and read noise
    same = images({"marine_snow": "strong"}, noise=False, draws=eff)
    other = images({"marine_snow": "strong"}, noise=False)
    # without the falloff the corners gain against the centre (the dive's exposure, set on the panel, moves both)
    ratio = (same + 1) / (clean + 1)
    assert ratio[:, :15, :15].mean() > 1.3 * ratio[:, 50:70, 70:90].mean()

    def fine(d):            # what is left of a difference image above its 7x7 median: the particles' specks
        from scipy.ndimage import median_filter

        g = d.mean(axis=-1)
        return np.abs(g - median_filter(g, size=(1, 7, 7))).mean()

    # (measured: 0.27 with the same draws, the exposure's change on the panel's texture; 0.98 with others)
    assert fine(other - clean) > 2 * fine(same - clean)           # the same particles, not others
