"""The node executables (``setup.py`` console scripts): each imports its node module only after the
stop signals are handled (:func:`uw_sil.nodes.start_node`).

Importing a node module loads rclpy, scipy and the renderer: 1-3 s, longer on a loaded machine. A launch
that ends in that time (another node failed, Ctrl-C) sends SIGINT to a node still importing; raised inside
the import, the KeyboardInterrupt printed a traceback and the process died with -2 instead of finishing
cleanly like a node stopped while it runs (seen in CI: ``bag_play`` failed on a missing bag while
``backward_fit`` was still importing scipy). Here a stop signal during the import ends the process with
code 0 and nothing printed, the same as a stop during :func:`uw_sil.nodes.run_node`.

``python -m uw_sil.nodes.entry NODE [ARGS]`` starts the same way (what ``uw-sil launch`` runs).
"""
from __future__ import annotations

import sys

from . import NODES, start_node as start


def sim_camera() -> int:
    return start("sim_camera")


def backward_fit() -> int:
    return start("backward_fit")


def bag_play() -> int:
    return start("bag_play")


def enhancer() -> int:
    return start("enhancer")


def panel_pose() -> int:
    return start("panel_pose")


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in NODES:
        sys.exit(f"usage: python -m uw_sil.nodes.entry NODE [ARGS] (NODE: {', '.join(NODES)})")
    sys.exit(start(sys.argv.pop(1)))
