"""Same input, same result: a backward fit is bit-identical between calls in one process and across processes."""
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import uw_sil
from uw_sil.fit.backward import fit_bag
from uw_sil.sim.camera import CameraModel
from uw_sil.bags.synth import synthesize_trial

SMALL = CameraModel.from_fov(160, 120, 70.0)
# From the centre of the bounds, so that the search itself (its seed, its steps) decides the result.
FITS = {
    "cmaes": dict(k=2, stride=4, method="cmaes", max_iter=4, swarm_size=8, seed=3, x0=None),
    "pso": dict(k=2, stride=4, method="pso", max_iter=3, swarm_size=8, seed=3, x0=None),
}


def fingerprint(fit) -> dict:
    """Everything a fit decided, as exact (hex) floats and a hash of every evaluation."""
    o = fit.optim
    evaluations = hashlib.sha256(o.evaluations.x.tobytes() + o.evaluations.f.tobytes()).hexdigest()
    return {"x_best": [float(v).hex() for v in fit.x_best], "theta_best": float(fit.theta_best).hex(),
            "theta_start": float(fit.theta_start).hex(), "n_evals": int(o.n_evals), "stop_reason": o.stop_reason,
            "evaluations": evaluations}


_CHILD = """
import json, sys
sys.path.insert(0, sys.argv[2])
from test_reproducible import FITS, fingerprint
from uw_sil.fit.backward import fit_bag
print(json.dumps({m: fingerprint(fit_bag(sys.argv[1], **o)) for m, o in FITS.items()}))
"""


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    out = tmp_path_factory.mktemp("repro") / "trial.mcap"
    synthesize_trial(out, n_frames=6, seed=11, camera=SMALL)
    return out


@pytest.fixture(scope="module")
def other_process(trial):
    env = {**os.environ, "PYOPENGL_PLATFORM": "osmesa",
           "PYTHONPATH": os.pathsep.join([str(Path(uw_sil.__file__).resolve().parents[1]),
                                          os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-c", _CHILD, str(trial), str(Path(__file__).parent)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("method", sorted(FITS))
def test_fit_is_bit_identical_in_one_process_and_across_processes(trial, other_process, method):
    first = fingerprint(fit_bag(trial, **FITS[method]))
    second = fingerprint(fit_bag(trial, **FITS[method]))
    assert float.fromhex(first["theta_best"]) > float.fromhex(first["theta_start"])  # the search moved
    assert second == first, "two fits in one process differ"
    assert other_process[method] == first, "a fit in another process differs"
