"""Restoring real frames: dehazing baselines and their evaluation by feature matches.

The forward half of the paper (issue 8): real frames are dehazed with the simulated depth (SIL) and
compared with the dark channel prior (:mod:`.dcp`: DCP, UDCP) by counting feature matches between
frames (:mod:`.features`: ORB, BRIEF, SIFT, SURF, KAZE, AKAZE; paper Table 2 / Fig. 5).
Submodules are imported on first use of a name.

Import rules: may import :mod:`uw_sil.sim`, :mod:`uw_sil.metrics`, :mod:`uw_sil.bags`,
:mod:`uw_sil._shared` and :mod:`uw_sil.viz` (numpy, OpenCV, mahotas); never fit or the ROS nodes.
"""
from __future__ import annotations

import importlib

__all__ = [
    "ALL_DESCRIPTORS",
    "DehazeResult",
    "MatchResult",
    "dehaze_dcp",
    "draw_matches",
    "match_features",
    "match_table",
    "table_csv",
    "table_markdown",
]

_WHERE = {
    "DehazeResult": "dcp",
    "dehaze_dcp": "dcp",
    "ALL_DESCRIPTORS": "features",
    "MatchResult": "features",
    "draw_matches": "features",
    "match_features": "features",
    "match_table": "features",
    "table_csv": "features",
    "table_markdown": "features",
}


def __getattr__(name):
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
