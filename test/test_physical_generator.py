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
