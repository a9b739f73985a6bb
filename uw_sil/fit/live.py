"""The diagnosis at dive start, on a live stream: what the ``backward_fit`` node needs beyond
:func:`uw_sil.fit.diagnose.diagnose_frames` (no ROS here; the node converts these results to messages).

* :class:`SpreadCollector`: keeps the paired frames of the stream (image, camera, pose) until the input ends or
  ``max_scan`` frames came, then picks ``k`` spread over all of them with
  :func:`uw_sil.fit.residuals.frames_from_samples`, the selection ``uw-sil diagnose`` makes over a bag: a bag
  replayed into the node gives the diagnosis the same frames as the command given the bag.
* :func:`extended_parameters`: the ``sim_camera`` parameters of the extended model, read back from the file
  :func:`uw_sil.fit.diagnose.write_diagnosis_yaml` writes (one writer for the file and the live parameters:
  a ``sim_camera`` started with ``--params-file`` of that file and one re-parameterized live hold the same).
* :func:`diagnostic_statuses` / :func:`failure_statuses`: the diagnosis JSON as ``diagnostic_msgs`` statuses
  (level, name, message, key/values), one per effect judged plus a summary.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

__all__ = ["SpreadCollector", "extended_parameters", "diagnostic_statuses", "failure_statuses", "OK", "WARN",
           "ERROR", "STATUS_PREFIX"]

#: ``diagnostic_msgs/DiagnosticStatus`` levels (the message's constants, as names).
OK, WARN, ERROR = "OK", "WARN", "ERROR"

#: Status names start with this (``/diagnostics`` is shared by every node of a vehicle).
STATUS_PREFIX = "uw_sil diagnosis"


class SpreadCollector:
    """Collect the frames of a live stream for the diagnosis; pick ``k`` spread over everything collected.

    Parameters
    ----------
    k : int
        Frames the diagnosis uses (``uw-sil diagnose --frames``).
    max_scan : int
        Frames kept at most; the collection is ``done`` then (a live camera: the approach must fit in
        ``max_scan`` frames; a replayed bag usually ends first, see the node's ``idle_timeout``). Each frame is
        kept in full until the selection (640x480: 0.9 MB).
    min_coverage : float
        Frames on which the scene model covers less than this are replaced by others (as offline).
    """

    def __init__(self, k: int = 8, max_scan: int = 200, min_coverage: float = 0.01):
        if k < 3:
            raise ValueError(f"the diagnosis needs at least 3 frames (diagnose_frames), got {k}")
        if max_scan < k:
            raise ValueError(f"max_scan ({max_scan}) must be >= the frames diagnosed ({k})")
        if not 0 <= min_coverage < 1:
            raise ValueError("min_coverage must be in [0, 1)")
        self.k, self.max_scan, self.min_coverage = int(k), int(max_scan), float(min_coverage)
        self.samples: list = []

    @property
    def scanned(self) -> int:
        return len(self.samples)

    @property
    def done(self) -> bool:
        return self.scanned >= self.max_scan

    def offer(self, sample) -> bool:
        """Keep the next paired frame of the stream (its index is its position in the stream); False when done."""
        if self.done:
            return False
        self.samples.append((self.scanned, sample))
        return True

    def frames(self, model=None, renderer=None) -> list:
        """The ``k`` frames of the diagnosis and up to :data:`uw_sil.fit.diagnose.REPORT_FRAMES` report frames
        (when enough came; as ``uw-sil diagnose`` reads a bag), rendered at their poses
        (:func:`frames_from_samples`); ValueError when fewer than 2 show the scene model. Pass
        ``report_frames=report_count(len(frames), k)`` to the diagnosis."""
        from .diagnose import REPORT_FRAMES
        from .residuals import frames_from_samples

        return frames_from_samples(self.samples, self.k + REPORT_FRAMES, model=model, min_coverage=self.min_coverage,
                                   renderer=renderer, what=f"the {self.scanned} frames received")


def extended_parameters(diag, fog: str = "exp2") -> dict:
    """``sim_camera`` parameters of the diagnosis' final model (base, ``fog_mode``, ``noise_sigma``, ``effects``
    and every ``<effect>.<param>`` of the accepted effects): the ``ros__parameters`` of the file
    :func:`uw_sil.fit.diagnose.write_diagnosis_yaml` writes, read back."""
    import yaml

    from .diagnose import write_diagnosis_yaml

    with tempfile.TemporaryDirectory(prefix="uw_sil_diag_") as tmp:
        path = Path(tmp) / "extended.yaml"
        write_diagnosis_yaml(path, diag, fog=fog)
        doc = yaml.safe_load(path.read_text())
    return dict(doc["/**"]["ros__parameters"])


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return "; ".join(_fmt(x) for x in v)
    return str(v)


def diagnostic_statuses(doc: dict, node: str = "backward_fit") -> list:
    """The statuses of a diagnosis (its JSON document, :meth:`uw_sil.fit.diagnose.Diagnosis.to_json`).

    A summary (``OK`` when no effect is needed, ``WARN`` when the model was extended), then one per effect
    judged, in the order first judged: ``WARN`` for an accepted effect (its explanation; its confidence,
    doubts and fitted parameters as key/values), ``OK`` for one that was not needed (its best held-out gain
    against its margin) or is undecided (``undecided`` of the document: it beat its margin, and the final
    model's effects explain it as well). Each is a dict ``level``, ``name``, ``message``, ``hardware_id``,
    ``values`` (``{key: text}``)."""
    verdict = {v["effect"]: v for v in doc.get("verdict", [])}
    base, final = doc["base"], doc["final"]
    theta = f"held-out θ {base['theta_heldout']:.4f} -> {final['theta_heldout']:.4f}"
    summary_values = {"theta_heldout_base": base["theta_heldout"], "theta_heldout_final": final["theta_heldout"],
                      "effects": ",".join(final.get("effects", [])) or "none",
                      "time_s": doc.get("timing", {}).get("total_s", float("nan"))}
    if final.get("camera_noise"):                              # what sim_camera draws as the camera's noise
        summary_values["camera_noise"] = final["camera_noise"]["model"]
    if final.get("theta_heldout_simulated") is not None:       # as sim_camera renders the models
        summary_values.update(theta_heldout_simulated_base=base["theta_heldout_simulated"],
                              theta_heldout_simulated_final=final["theta_heldout_simulated"])
    if verdict:
        summary = (WARN, f"the simulation lacks {', '.join(verdict)}: extended model sent ({theta})")
    else:
        summary = (OK, f"none: no effect raised held-out θ beyond the noise margin ({theta})")
    out = [_status(summary[0], f"{STATUS_PREFIX}", summary[1], node, summary_values)]
    judged: dict = {}
    for c in doc.get("candidates", []):
        judged.setdefault(c["effect"], []).append(c)
    undecided = {u["effect"]: u for u in doc.get("undecided", [])}
    for effect, rows in judged.items():
        if effect in verdict:
            v = verdict[effect]
            values = {"confidence": v["confidence"], **v["params"]}
            if v.get("doubts"):
                values["doubts"] = v["doubts"]
            out.append(_status(WARN, f"{STATUS_PREFIX}: {effect}", v["explanation"], node, values))
            continue
        if effect in undecided:         # evidence the final model's effects explain as well (diagnose.py)
            u = undecided[effect]
            out.append(_status(OK, f"{STATUS_PREFIX}: {effect}", f"undecided, not named: {u['explanation']}", node,
                               {"delta_heldout": u["delta_heldout"], "margin": u["margin"], "round": u["round"]}))
            continue
        best = max(rows, key=lambda c: c["delta_heldout"])
        crit = "held-out statistic" if best.get("criterion") == "statistic" else "held-out θ"
        gain, margin = best["delta_heldout"], best.get("margin", 0.0)
        message = (f"not needed: {crit} gain {gain:+.4f} below its margin {margin:.4f}" if gain < margin else
                   f"not accepted: {crit} gain {gain:+.4f} beat its margin {margin:.4f}, but another effect "
                   f"was chosen or its own test refused it (candidates in ~/diagnosis)")
        out.append(_status(OK, f"{STATUS_PREFIX}: {effect}", message, node,
                           {"delta_heldout": best["delta_heldout"], "margin": best.get("margin", 0.0),
                            "round": best.get("round", 1)}))
    return out


def failure_statuses(reason: str, node: str = "backward_fit") -> list:
    """The status of a diagnosis that could not be made (``ERROR``, with the reason)."""
    return [_status(ERROR, STATUS_PREFIX, f"could not diagnose: {reason}", node, {})]


def _status(level: str, name: str, message: str, node: str, values: dict) -> dict:
    return {"level": level, "name": name, "message": message, "hardware_id": node,
            "values": {k: _fmt(v) for k, v in values.items()}}
