"""uw_sil: an underwater camera simulation fitted to what a real ROV camera sees.

Rooms (subpackages), each with its import rules in its ``__init__``:

- :mod:`uw_sil.sim`      the simulated camera: camera, poses, scene, renderer, underwater model, noise
- :mod:`uw_sil.metrics`  image-quality criteria: FSIM/FSIMc, HSV histograms, theta
- :mod:`uw_sil.fit`      optimizers, the backward fit and its report
- :mod:`uw_sil.bags`     ROS 2 bags: reading, writing, stamp pairing, synthetic trials
- :mod:`uw_sil.nodes`    the ROS 2 room: rclpy nodes, the node graphs and their launcher (only room importing rclpy)
- :mod:`uw_sil._shared`  small helpers: input checks, atomic file writes

``uw_sil.cli`` is the ``uw-sil`` command; ``uw_sil.viz`` draws figures. The names users type most
are re-exported here lazily (importing uw_sil loads nothing heavy).
"""
from ._shared.lazy import lazy_getattr

__version__ = "0.1.0"

_EXPORTS = {
    "CameraModel": "sim", "Renderer": "sim", "SimCamera": "sim", "UnderwaterParams": "sim", "facing_pose": "sim",
    "fit_bag": "fit", "read_samples": "bags", "synthesize_trial": "bags", "write_trial": "bags",
}
__all__ = sorted(_EXPORTS)

__getattr__ = lazy_getattr(__name__, _EXPORTS)
