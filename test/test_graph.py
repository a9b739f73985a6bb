"""The pure parts of starting node graphs: uw_sil.nodes.graph (descriptions, command lines) and uw_sil.nodes.launcher
(process supervision), the latter with a fake interpreter standing in for the nodes (no ROS here)."""
import io
import os
import signal
import stat
import sys
import time

import pytest

from uw_sil.nodes import graph, launcher
from uw_sil.nodes.graph import NodeSpec


def test_backward_graph_with_a_bag_ends_with_the_fit():
    specs = graph.backward_graph(bag="/data/trial.mcap", output_yaml="/tmp/fit.yaml", frames=2, optimizer="cmaes",
                                 rate=2.0, max_iter=40)
    by_name = {s.name: s for s in specs}
    assert list(by_name) == ["sim_camera", "backward_fit", "bag_play"]
    fit, play = by_name["backward_fit"], by_name["bag_play"]
    assert fit.required and fit.parameters["exit_when_done"] is True
    assert fit.parameters["max_iter"] == 40 and "stride" not in fit.parameters
    assert not play.required and not by_name["sim_camera"].required
    assert play.parameters["rate"] == 2.0 and play.parameters["bag"] == "/data/trial.mcap"
    # bag_play waits for the fitting node's subscriptions to the bag's topics (not any subscriber's)
    assert set(play.parameters["wait_for_topics"]) <= set(graph.BACKWARD_INPUTS)
    assert play.parameters["wait_for_nodes"] == ["backward_fit"]
    # a bag with fewer usable frames than asked for still ends in a fit
    assert fit.parameters["idle_timeout"] == graph.IDLE_TIMEOUT > 0
    assert by_name["sim_camera"].param_files == [str(graph.share_file("config", "sim_camera.yaml"))]


@pytest.mark.parametrize("kwargs", [{}, {"bag": "t.mcap", "keep_running": True}])
def test_live_or_keep_running_graphs_run_until_stopped(kwargs):
    specs = graph.backward_graph(**kwargs)
    assert not any(s.required for s in specs)
    assert all(s.parameters.get("exit_when_done", False) is False for s in specs)
    assert ("idle_timeout" in specs[1].parameters) == ("bag" in kwargs)
    assert ("bag_play" in [s.name for s in specs]) == ("bag" in kwargs)


def test_command_line_quotes_values_as_yaml():
    spec = NodeSpec("bag_play", "player", param_files=["/p.yaml"],
                    parameters={"bag": "/a b/true.mcap", "empty": "", "yes": "true", "flag": False, "n": 3,
                                "x": 0.5, "topics": ["/a", "/b"]},
                    remappings=[("in", "out")])
    cmd = graph.command_line(spec, python="/py")
    assert cmd[:3] == ["/py", "-m", "uw_sil.nodes.bag_play"]
    args = cmd[3:]
    assert args[:4] == ["--ros-args", "-r", "__node:=player", "--params-file"]
    p = [args[i + 1] for i, a in enumerate(args) if a == "-p"]
    # strings stay strings (quoted), even when they look like YAML booleans or are empty
    assert p == ['bag:="/a b/true.mcap"', 'empty:=""', 'yes:="true"', "flag:=false", "n:=3", "x:=0.5",
                 'topics:=["/a", "/b"]']
    assert args[-2:] == ["-r", "in:=out"]


def test_share_file_finds_the_fastdds_profile():
    f = graph.share_file("config", "fastdds_shm.xml")
    assert f.is_file() and "segment_size" in f.read_text()
    with pytest.raises(FileNotFoundError, match="nope.xml"):
        graph.share_file("config", "nope.xml")


# ------------------------------------------------------------------------------------------ launcher

FAKE_PYTHON = r"""#!/bin/bash
# Stands in for `python -m uw_sil.nodes.NAME --ros-args ...`: behaves according to NAME. A long-running
# node creates the file $READY once its signal traps are set; quick and fail wait for it (when READY is
# set), so the launcher never signals a node that has not yet installed its traps, however busy the machine.
name="${2#uw_sil.nodes.}"
echo "profile=$FASTDDS_DEFAULT_PROFILES_FILE"
echo -n "partial line without newline"; echo " completed"
wait_ready() { if [ -n "$READY" ]; then while [ ! -e "$READY" ]; do sleep 0.02; done; fi; }
ready() { if [ -n "$READY" ]; then touch "$READY"; fi; }
case "$name" in
  quick) wait_ready; sleep 0.2; echo "finished"; exit 0 ;;
  fail) wait_ready; sleep 0.2; echo "something broke" >&2; exit 3 ;;
  stubborn) trap '' INT TERM; ready; echo "ignoring signals"; while :; do sleep 0.05; done ;;
  *) trap 'echo "got SIGINT"; exit 0' INT; ready; echo "trapping SIGINT"; while :; do sleep 0.05; done ;;
esac
"""


class SignalOn(io.StringIO):
    """Launcher output that sends this process SIGINT (a Ctrl-C) each time the next of ``triggers`` appears
    in it: the test reacts to what the launcher did, not to a timer racing it."""

    def __init__(self, *triggers):
        super().__init__()
        self.triggers = list(triggers)

    def write(self, text):
        n = super().write(text)
        while self.triggers and self.triggers[0] in self.getvalue():
            self.triggers.pop(0)
            os.kill(os.getpid(), signal.SIGINT)
        return n


@pytest.fixture
def fake_python(tmp_path):
    p = tmp_path / "python"
    p.write_text(FAKE_PYTHON)
    p.chmod(p.stat().st_mode | stat.S_IXUSR)
    return str(p)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _pids(text: str) -> list:
    return [int(line.split("(pid ")[1].split(")")[0]) for line in text.splitlines() if "(pid " in line]


def test_required_node_ends_the_graph(fake_python, tmp_path):
    out = io.StringIO()
    rc = launcher.launch([NodeSpec("server", "server"), NodeSpec("quick", "quick", required=True)],
                         env={"PATH": os.environ["PATH"], "READY": str(tmp_path / "ready")}, out=out,
                         python=fake_python)
    text = out.getvalue()
    assert rc == 0, text
    assert "[quick ] finished" in text                     # output prefixed with the (padded) node name
    assert "[server] partial line without newline completed" in text
    assert "[server] got SIGINT" in text                   # the others were stopped with SIGINT
    assert "required node quick ended" in text and "all nodes ended cleanly" in text
    profile = str(graph.share_file("config", "fastdds_shm.xml"))
    assert f"[server] profile={profile}" in text
    assert not any(_alive(p) for p in _pids(text))


def test_a_node_that_ends_normally_does_not_end_the_graph(fake_python, tmp_path):
    out = SignalOn("quick exited with status 0")        # Ctrl-C once quick has ended
    rc = launcher.launch([NodeSpec("server", "server"), NodeSpec("quick", "quick")],
                         env={"PATH": os.environ["PATH"], "FASTDDS_DEFAULT_PROFILES_FILE": "/mine.xml",
                              "READY": str(tmp_path / "ready")}, out=out, python=fake_python)
    text = out.getvalue()
    # the server kept running after `quick` ended, until Ctrl-C, which it got once and obeyed
    assert rc == 0, text
    assert text.index("quick exited with status 0") < text.index("SIGINT received: stopping server")
    assert text.count("[server] got SIGINT") == 1
    assert "[server] profile=/mine.xml" in text            # a profile chosen by the caller is kept
    assert not any(_alive(p) for p in _pids(text))


def test_failing_node_stops_the_graph_with_an_error(fake_python, tmp_path):
    out = io.StringIO()
    rc = launcher.launch([NodeSpec("server", "server"), NodeSpec("fail", "fail")],
                         env={"PATH": os.environ["PATH"], "READY": str(tmp_path / "ready")}, out=out,
                         python=fake_python)
    text = out.getvalue()
    assert rc == 1
    assert "[fail  ] something broke" in text               # stderr is shown too
    assert "fail exited with status 3 (FAILED)" in text and "fail failed: stopping server" in text
    assert "FAILED: fail" in text


def test_node_ignoring_signals_is_killed_and_reported(fake_python, tmp_path):
    out = io.StringIO()
    t0 = time.monotonic()
    rc = launcher.launch([NodeSpec("stubborn", "stubborn"), NodeSpec("quick", "quick", required=True)],
                         env={"PATH": os.environ["PATH"], "READY": str(tmp_path / "ready")}, out=out,
                         python=fake_python, stop_timeout=0.3)
    text = out.getvalue()
    assert rc == 1, text
    assert "sending SIGTERM" in text and "sending SIGKILL" in text and "killed by SIGKILL" in text
    assert time.monotonic() - t0 < 5
    assert not any(_alive(p) for p in _pids(text))


def test_repeated_ctrl_c_escalates_at_once(fake_python):
    # Ctrl-C once the node ignores signals, again once the launcher is stopping it, a third time after SIGTERM
    out = SignalOn("[stubborn] ignoring signals", "SIGINT received: stopping stubborn", "sending SIGTERM")
    t0 = time.monotonic()
    rc = launcher.launch([NodeSpec("stubborn", "stubborn")], env={"PATH": os.environ["PATH"]}, out=out,
                         python=fake_python, stop_timeout=60)
    text = out.getvalue()
    assert rc == 1 and "sending SIGTERM" in text and "sending SIGKILL" in text, text
    assert time.monotonic() - t0 < 10                      # not 2 x stop_timeout
    assert not any(_alive(p) for p in _pids(text))


def test_launch_rejects_bad_graphs():
    with pytest.raises(ValueError, match="empty"):
        launcher.launch([])
    with pytest.raises(ValueError, match="unique"):
        launcher.launch([NodeSpec("a", "x"), NodeSpec("b", "x")])


def test_cli_has_launch_and_play():
    from uw_sil.cli import build_parser

    args = build_parser().parse_args(["launch", "backward", "--bag", "t.mcap", "--frames", "2", "--optimizer",
                                      "cmaes", "--rate", "0.5", "--output-yaml", "f.yaml"])
    assert args.func is launcher.cmd_launch and args.graph == "backward" and args.rate == 0.5
    args = build_parser().parse_args(["play", "t.mcap", "--loop", "--rate", "2"])
    assert args.func is launcher.cmd_play and args.loop and args.rate == 2.0
    with pytest.raises(SystemExit):
        build_parser().parse_args(["play", "t.mcap", "--rate", "0"])


def test_launch_file_maps_the_graph_to_launch_ros(monkeypatch):
    """launch/launch_ros are not on PyPI: run backward.launch.py against minimal stand-ins that record
    what it builds, to check that it passes the graph through (names, parameters, required -> Shutdown)."""
    import importlib.util
    import types

    class Recorder:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    class LaunchConfiguration(Recorder):
        def perform(self, context):
            return context[self.args[0]]

    class Shutdown(Recorder):
        pass

    fake = {"launch": types.ModuleType("launch"), "launch.actions": types.ModuleType("launch.actions"),
            "launch.substitutions": types.ModuleType("launch.substitutions"),
            "launch_ros": types.ModuleType("launch_ros"), "launch_ros.actions": types.ModuleType("launch_ros.actions")}
    fake["launch"].LaunchDescription = lambda actions: actions
    for name in ("DeclareLaunchArgument", "OpaqueFunction", "SetEnvironmentVariable"):
        setattr(fake["launch.actions"], name, type(name, (Recorder,), {}))
    fake["launch.actions"].Shutdown = Shutdown
    fake["launch.substitutions"].LaunchConfiguration = LaunchConfiguration
    fake["launch_ros.actions"].Node = type("Node", (Recorder,), {})
    for k, v in fake.items():
        monkeypatch.setitem(sys.modules, k, v)
    path = graph.share_file("launch", "backward.launch.py")
    spec = importlib.util.spec_from_file_location("backward_launch", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    actions = mod.generate_launch_description()
    context = {a.args[0]: a.kwargs["default_value"] for a in actions if type(a).__name__ == "DeclareLaunchArgument"}
    env = next(a for a in actions if type(a).__name__ == "SetEnvironmentVariable")
    assert env.args == ("FASTDDS_DEFAULT_PROFILES_FILE", str(graph.share_file("config", "fastdds_shm.xml")))
    opaque = next(a for a in actions if type(a).__name__ == "OpaqueFunction").kwargs["function"]

    nodes = opaque(context)                                    # defaults: live graph, runs until stopped
    assert [n.kwargs["name"] for n in nodes] == ["sim_camera", "backward_fit"]
    assert all(n.kwargs["on_exit"] is None for n in nodes)

    context.update(bag="/d/t.mcap", max_iter="7", output_yaml="/d/fit.yaml")
    nodes = {n.kwargs["name"]: n.kwargs for n in opaque(context)}
    specs = {s.name: s for s in graph.backward_graph(bag="/d/t.mcap", max_iter=7, output_yaml="/d/fit.yaml")}
    assert set(nodes) == set(specs)
    for name, s in specs.items():
        assert nodes[name]["executable"] == s.executable and nodes[name]["package"] == "uw_sil"
        assert nodes[name]["parameters"] == [*s.param_files, s.parameters]
        assert isinstance(nodes[name]["on_exit"], Shutdown) == s.required
    assert isinstance(nodes["backward_fit"]["on_exit"], Shutdown)
