"""ROS 2 bags of field trials: reading (:mod:`.reader`, with cut-off MCAP recovery in
:mod:`.mcap_recover`), writing (:mod:`.writer`), stamp pairing (:mod:`.stamps`), image message
conversion (:mod:`.imgmsg`), synthetic trials (:mod:`.synth`), and what a field bag's frames, intrinsics
and poses come from (:mod:`.source`): camera_calibration YAML files and rectification
(:mod:`.camera_yaml`), recorded /tf and /tf_static (:mod:`.tf`), the panel's markers (via
:mod:`uw_sil.sim.markers`).

Import rules: may import :mod:`uw_sil.sim` (cameras, poses; the renderer for synthetic trials) and
:mod:`uw_sil._shared`; no metrics, fit or ROS nodes (messages are decoded with ``rosbags``, not rclpy).
"""
from .._shared.lazy import lazy_getattr

_EXPORTS = {
    "BagError": "records", "BagInfo": "reader", "RawMessage": "reader", "ReadReport": "reader", "Sample": "records",
    "StampSynchronizer": "stamps", "TopicInfo": "reader", "iter_messages": "reader", "iter_raw": "reader",
    "open_bag": "reader", "read_samples": "reader", "resolve_bag_path": "reader", "synthesize_trial": "synth",
    "write_trial": "writer", "BagSource": "source", "PoseFrom": "records", "describe_sources": "source",
    "CameraCalibration": "camera_yaml", "load_camera_yaml": "camera_yaml", "write_camera_yaml": "camera_yaml",
    "TransformBuffer": "tf", "load_tf": "reader",
}
__all__ = sorted(_EXPORTS)

__getattr__ = lazy_getattr(__name__, _EXPORTS)
