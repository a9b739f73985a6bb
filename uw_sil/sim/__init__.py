"""The simulated camera: pinhole camera and poses, the panel scene (and its fiducial markers, with the
panel pose from them: :mod:`.markers`, refined by face alignment: :mod:`.align`), the headless renderer,
the underwater image model with its parameters, camera noise, the effects the base model leaves out
(:mod:`.effects`) with the extended model (:class:`UnderwaterModel`), :class:`SimCamera` that puts
them together, and :class:`FrameStream` that makes its frames side by side (:mod:`.stream`).

Import rules: imports nothing of uw_sil but :mod:`uw_sil._shared` (no metrics, fit, bags, ROS).
Heavy modules (pyrender, trimesh) load only when their names are first used.
"""
from .._shared.lazy import lazy_getattr

_EXPORTS = {
    "CameraModel": "camera", "FOG_MODES": "optics", "NoiseField": "noise", "ParamSpace": "params",
    "PreparedRender": "optics", "RenderResult": "render", "Renderer": "render", "SimCamera": "simcam",
    "SimFrame": "simcam", "UnderwaterParams": "params", "degrade": "optics", "estimate_noise_sigma": "noise",
    "facing_pose": "scene", "look_at": "transforms", "matrix_to_pose": "transforms", "pose_to_matrix": "transforms",
    "UnderwaterModel": "model", "Geometry": "model", "parse_effects": "effects", "EFFECTS": "effects",
    "MarkerLayout": "markers", "MarkerPoseEstimator": "markers", "load_marker_layout": "markers",
    "FaceAligner": "align", "FrameStream": "stream",
}
__all__ = sorted(_EXPORTS)

__getattr__ = lazy_getattr(__name__, _EXPORTS)
