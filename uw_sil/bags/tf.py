"""A transform buffer for recorded ``/tf`` and ``/tf_static``: chain through the tree, interpolate in time.

A field bag rarely has the panel's pose in the camera frame; it has the vehicle's navigation
(``world -> base_link`` on ``/tf``), the camera mount (``base_link -> camera_optical_frame`` on
``/tf_static``) and, when someone surveyed it, the panel (``world -> panel``). :class:`TransformBuffer`
holds these edges and answers ``lookup("camera_optical_frame", "panel", stamp)`` -- the panel frame
expressed in the camera frame, ``T_cam_panel`` -- by composing the transforms along the tree path through
the frames' common ancestor, each dynamic edge interpolated to the stamp (linear in translation,
spherical-linear in rotation [1]_). It is tf2's ``lookupTransform(target, source, time)`` without ROS. A bag's
transforms are read into one by :func:`uw_sil.bags.reader.load_tf`.

Conventions (tf2): a ``geometry_msgs/TransformStamped`` with ``header.frame_id = parent`` and
``child_frame_id = child`` is the child frame's pose in the parent frame, ``T_parent_child`` (maps points
from child to parent coordinates). Leading slashes of frame names are dropped, as tf2 does.

Unlike tf2, a stamp slightly outside the recorded span of an edge is accepted (the edge's first or last
transform is held) up to ``extrapolation_s``; beyond that, or inside a recording gap longer than
``max_gap_s``, the lookup is refused with :class:`TfExtrapolationError` naming the edge and the times.

References
----------
.. [1] K. Shoemake, "Animating rotation with quaternion curves", Proc. SIGGRAPH 1985, 245-254.
.. [2] T. Foote, "tf: The transform library", Proc. IEEE TePRA 2013 (tf/tf2's design).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..sim.transforms import pose_to_matrix
from .records import BagError

__all__ = ["TransformBuffer", "TfError", "TfExtrapolationError", "slerp", "TF_TOPICS"]

#: Topics read by :func:`uw_sil.bags.reader.load_tf`: dynamic and static transforms.
TF_TOPICS = ("/tf", "/tf_static")


class TfError(BagError):
    """The transform tree cannot answer: unknown frame, disconnected tree, inconsistent parents."""


class TfExtrapolationError(TfError):
    """A stamp outside what an edge recorded (beyond the tolerance), or inside a gap of its recording."""


def slerp(q0, q1, u: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions ``q0`` (u = 0) and ``q1`` (u = 1).

    Takes the shorter arc (``q`` and ``-q`` are the same rotation) and falls back to a normalized linear
    interpolation when the quaternions are nearly equal. Quaternions are (x, y, z, w).

    References
    ----------
    .. [1] K. Shoemake, "Animating rotation with quaternion curves", Proc. SIGGRAPH 1985, 245-254.
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(1.0, d))
    s = np.sin(theta)
    return (np.sin((1.0 - u) * theta) * q0 + np.sin(u * theta) * q1) / s


def _norm_frame(name) -> str:
    return str(name).lstrip("/")


@dataclass
class _Edge:
    parent: str
    static: bool
    stamps: list = field(default_factory=list)
    trans: list = field(default_factory=list)
    quats: list = field(default_factory=list)
    _arrays: tuple | None = None

    def arrays(self):
        if self._arrays is None:
            order = np.argsort(np.asarray(self.stamps, dtype=np.int64), kind="stable")
            st = np.asarray(self.stamps, dtype=np.int64)[order]
            tr = np.asarray(self.trans, dtype=float)[order]
            qs = np.asarray(self.quats, dtype=float)[order]
            # several transforms with one stamp: the last one received wins (as in tf2)
            keep = np.append(st[1:] != st[:-1], True)
            self._arrays = (st[keep], tr[keep], qs[keep])
        return self._arrays


class TransformBuffer:
    """Transforms of a recording, queried like tf2's ``lookupTransform``.

    Parameters
    ----------
    extrapolation_s : float
        How far (seconds) a stamp may lie before the first or after the last transform of a dynamic
        edge; the first/last transform is then used. Beyond it the lookup is refused.
    max_gap_s : float
        Longest interval (seconds) between two transforms of a dynamic edge that is interpolated across.
    """

    def __init__(self, extrapolation_s: float = 0.1, max_gap_s: float = 1.0):
        if not (extrapolation_s >= 0 and max_gap_s > 0):
            raise ValueError(f"need extrapolation_s >= 0 and max_gap_s > 0, got {extrapolation_s}, {max_gap_s}")
        self.extrapolation_ns = int(round(extrapolation_s * 1e9))
        self.max_gap_ns = int(round(max_gap_s * 1e9))
        self._edges: dict[str, _Edge] = {}
        self.source = "tf"

    # ------------------------------------------------------------------ filling

    def add(self, parent: str, child: str, stamp_ns: int, translation, quaternion_xyzw, static: bool = False) -> None:
        """Add ``T_parent_child`` at ``stamp_ns`` (static transforms hold at all times)."""
        parent, child = _norm_frame(parent), _norm_frame(child)
        if not parent or not child:
            raise TfError(f"{self.source}: a transform has an empty frame name ({parent!r} -> {child!r})")
        if parent == child:
            raise TfError(f"{self.source}: transform from frame {child!r} to itself")
        q = np.asarray(quaternion_xyzw, dtype=float)
        n = np.linalg.norm(q)
        if q.shape != (4,) or not np.isfinite(q).all() or n < 1e-9:
            raise TfError(f"{self.source}: transform {parent} -> {child} has an invalid rotation {list(q)}")
        t = np.asarray(translation, dtype=float)
        if t.shape != (3,) or not np.isfinite(t).all():
            raise TfError(f"{self.source}: transform {parent} -> {child} has an invalid translation {list(t)}")
        e = self._edges.get(child)
        if e is None:
            e = self._edges[child] = _Edge(parent, bool(static))
        elif e.parent != parent:
            raise TfError(f"{self.source}: frame {child!r} has two parents, {e.parent!r} and {parent!r} "
                          f"(a tf tree gives each frame one parent)")
        elif e.static != bool(static):
            raise TfError(f"{self.source}: {parent} -> {child} is published both on /tf and on /tf_static")
        if e.static:  # a static transform is replaced by a newer one, never interpolated
            e.stamps, e.trans, e.quats = [0], [t], [q / n]
        else:
            e.stamps.append(int(stamp_ns))
            e.trans.append(t)
            e.quats.append(q / n)
        e._arrays = None

    # ------------------------------------------------------------------ structure

    @property
    def frames(self) -> list[str]:
        """All frame names, sorted."""
        names = set(self._edges)
        names.update(e.parent for e in self._edges.values())
        return sorted(names)

    def parent(self, frame: str) -> str | None:
        e = self._edges.get(_norm_frame(frame))
        return None if e is None else e.parent

    def edges(self) -> list[tuple[str, str, bool, int]]:
        """``(parent, child, static, count)`` of every edge."""
        return [(e.parent, c, e.static, len(e.stamps)) for c, e in sorted(self._edges.items())]

    def _path_to_root(self, frame: str) -> list[str]:
        path = [frame]
        seen = {frame}
        while path[-1] in self._edges:
            p = self._edges[path[-1]].parent
            if p in seen:
                raise TfError(f"{self.source}: the transforms form a loop through {p!r}")
            path.append(p)
            seen.add(p)
        return path

    def _check_frame(self, frame: str) -> str:
        f = _norm_frame(frame)
        if f not in self._edges and all(e.parent != f for e in self._edges.values()):
            have = ", ".join(self.frames) or "none"
            raise TfError(f"frame {f!r} is not in {self.source}; its frames are: {have}")
        return f

    def chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Tree paths ``target -> ancestor`` and ``source -> ancestor`` (both ending at the common ancestor).

        Raises
        ------
        TfError
            A frame is unknown (the message lists the known frames), or the two frames are in different
            trees (a gap: no chain of transforms connects them).
        """
        target, source = self._check_frame(target), self._check_frame(source)
        pt, ps = self._path_to_root(target), self._path_to_root(source)
        if pt[-1] != ps[-1]:
            def tree(root):
                return sorted(f for f in self.frames if self._path_to_root(f)[-1] == root)
            raise TfError(f"tf tree has a gap: no chain of transforms connects {target!r} and {source!r} in "
                          f"{self.source} ({target!r} is in the tree of {pt[-1]!r}: {', '.join(tree(pt[-1]))}; "
                          f"{source!r} is in the tree of {ps[-1]!r}: {', '.join(tree(ps[-1]))})")
        common = next(f for f in pt if f in set(ps))
        return pt[: pt.index(common) + 1], ps[: ps.index(common) + 1]

    # ------------------------------------------------------------------ queries

    def span_ns(self, target: str, source: str) -> tuple[int | None, int | None]:
        """Stamps between which every dynamic edge of the chain has data (``None``: all static)."""
        up, down = self.chain(target, source)
        lo = hi = None
        for path in (up, down):
            for child in path[:-1]:
                e = self._edges[child]
                if e.static:
                    continue
                st = e.arrays()[0]
                lo = st[0] if lo is None else max(lo, st[0])
                hi = st[-1] if hi is None else min(hi, st[-1])
        return (None if lo is None else int(lo), None if hi is None else int(hi))

    def _edge_at(self, child: str, stamp_ns: int) -> np.ndarray:
        e = self._edges[child]
        st, tr, qs = e.arrays()
        if e.static or len(st) == 1 and abs(stamp_ns - st[0]) <= self.extrapolation_ns:
            return pose_to_matrix(tr[0], qs[0])
        what = f"{e.parent} -> {child}"
        if stamp_ns < st[0] - self.extrapolation_ns or stamp_ns > st[-1] + self.extrapolation_ns:
            side, dt = ("before", (st[0] - stamp_ns) / 1e9) if stamp_ns < st[0] else ("after", (stamp_ns - st[-1]) / 1e9)
            raise TfExtrapolationError(
                f"tf {what} is recorded from {st[0] / 1e9:.3f} s to {st[-1] / 1e9:.3f} s; stamp {stamp_ns / 1e9:.3f} s "
                f"is {dt:.3f} s {side} (extrapolation refused beyond {self.extrapolation_ns / 1e9:g} s)")
        i = int(np.searchsorted(st, stamp_ns))
        if i < len(st) and st[i] == stamp_ns:
            return pose_to_matrix(tr[i], qs[i])
        if i == 0:
            return pose_to_matrix(tr[0], qs[0])
        if i == len(st):
            return pose_to_matrix(tr[-1], qs[-1])
        gap = st[i] - st[i - 1]
        if gap > self.max_gap_ns:
            raise TfExtrapolationError(
                f"tf {what} has a {gap / 1e9:.3f} s gap from {st[i - 1] / 1e9:.3f} s to {st[i] / 1e9:.3f} s around "
                f"stamp {stamp_ns / 1e9:.3f} s (interpolation refused across more than {self.max_gap_ns / 1e9:g} s)")
        u = (stamp_ns - st[i - 1]) / gap
        return pose_to_matrix(tr[i - 1] + u * (tr[i] - tr[i - 1]), slerp(qs[i - 1], qs[i], u))

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """``T_target_source`` at ``stamp_ns``: the source frame expressed in the target frame (4x4).

        ``lookup(camera_optical_frame, panel, t)`` is the panel pose in the camera, ``T_cam_panel``.

        Raises
        ------
        TfError
            Unknown frame or disconnected tree (see :meth:`chain`).
        TfExtrapolationError
            ``stamp_ns`` outside an edge's recording by more than ``extrapolation_s`` or inside a gap
            longer than ``max_gap_s``.
        """
        up, down = self.chain(target, source)
        stamp_ns = int(stamp_ns)
        T_anc_target = np.eye(4)
        for child in reversed(up[:-1]):        # ancestor -> ... -> target
            T_anc_target = T_anc_target @ self._edge_at(child, stamp_ns)
        T_anc_source = np.eye(4)
        for child in reversed(down[:-1]):
            T_anc_source = T_anc_source @ self._edge_at(child, stamp_ns)
        R, t = T_anc_target[:3, :3], T_anc_target[:3, 3]
        inv = np.eye(4)
        inv[:3, :3] = R.T
        inv[:3, 3] = -R.T @ t
        return inv @ T_anc_source
