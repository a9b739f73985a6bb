"""Twins of a trial (the ceiling of held-out θ in bench/bench_concealed.py): the same dive with other draws of
what is new in every frame. Each generator's recording must not change when its twin is written, and the twin
must differ from it by the draws only: the same poses, the same mean image, pixels apart by noise."""
import os
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

RANDOM = {"marine_snow": "strong", "sensor_noise": "strong"}


def _own(out, twin, effects):
    from uw_sil.bags.synth import synthesize_trial
    from uw_sil.sim.camera import CameraModel

    for path, draws in ((out, None), (twin, 5)):
        if path is not None:
            synthesize_trial(path, n_frames=2, seed=3, camera=CameraModel.from_fov(160, 120, 70.0),
                             effects=effects, overwrite=True, draw_seed=draws)


def _foreign(out, twin, effects):
    from foreign_effects import synth_foreign

    synth_foreign(out, effects, n_frames=2, seed=3, width=160, twin_out=twin)


def _physical(out, twin, effects):
    from physical_effects import synth_physical

    synth_physical(out, effects, n_frames=2, seed=3, width=160, bs_step=16, twin_out=twin)


@pytest.mark.parametrize("gen", [_own, _foreign, _physical], ids=["own", "foreign", "physical"])
@pytest.mark.parametrize("effects", [{}, {**RANDOM, "vignetting": "strong"}], ids=["base", "random"])
def test_a_twin_changes_the_draws_only(tmp_path, gen, effects):
    from uw_sil.bags import read_samples

    gen(tmp_path / "alone.mcap", None, dict(effects))
    gen(tmp_path / "rec.mcap", tmp_path / "twin.mcap", dict(effects))
    alone, rec, twin = (list(read_samples(tmp_path / n)) for n in ("alone", "rec", "twin"))
    assert len(alone) == len(rec) == len(twin) == 2
    for a, r, t in zip(alone, rec, twin):
        assert np.array_equal(a.image, r.image)                 # the recording is the same with its twin
        assert np.array_equal(r.pose, t.pose) and r.stamp_ns == t.stamp_ns
        d = r.image.astype(float) - t.image.astype(float)
        assert np.abs(d).mean() > 0.2                            # other draws ...
        assert abs(d.mean()) < 0.05 * max(1.0, r.image.mean())  # ... of the same dive
