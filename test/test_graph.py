"""The pure parts of starting node graphs: uw_sil.nodes.graph (descriptions, command lines) and uw_sil.nodes.launcher
(process supervision), the latter with a fake interpreter standing in for the nodes (no ROS here)."""
import io
import os
import signal
import stat
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
    # ... and for sim_camera on the camera_info (the size of its renders; a short bag's are gone once played)
    assert play.parameters["wait_for_nodes"] == ["backward_fit", "sim_camera:/camera/camera_info"]
    # a bag with fewer usable frames than asked for still ends in a fit
    assert fit.parameters["idle_timeout"] == graph.IDLE_TIMEOUT > 0
    # the player publishes reliably and a replay must lose no frame: the fit reads reliably too
    assert fit.parameters["reliable_input"] is True
    assert by_name["sim_camera"].param_files == [str(graph.share_file("config", "sim_camera.yaml"))]


@pytest.mark.parametrize("kwargs", [{}, {"bag": "t.mcap", "keep_running": True}])
def test_live_or_keep_running_graphs_run_until_stopped(kwargs):
    specs = graph.backward_graph(**kwargs)
    assert not any(s.required for s in specs)
    assert all(s.parameters.get("exit_when_done", False) is False for s in specs)
    assert ("idle_timeout" in specs[1].parameters) == ("bag" in kwargs)
    assert specs[1].parameters.get("reliable_input", False) == ("bag" in kwargs)   # a live camera: best effort
    assert ("bag_play" in [s.name for s in specs]) == ("bag" in kwargs)


def test_command_line_quotes_values_as_yaml():
    spec = NodeSpec("bag_play", "player", param_files=["/p.yaml"],
                    parameters={"bag": "/a b/true.mcap", "empty": "", "yes": "true", "flag": False, "n": 3,
                                "x": 0.5, "topics": ["/a", "/b"]},
                    remappings=[("in", "out")])
    cmd = graph.command_line(spec, python="/py")
    assert cmd[:4] == ["/py", "-m", "uw_sil.nodes.entry", "bag_play"]
    args = cmd[4:]
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
# Stands in for `python -m uw_sil.nodes.entry NAME --ros-args ...`: behaves according to NAME. A long-running
# node creates the file $READY once its signal traps are set; quick and fail wait for it (when READY is
# set), so the launcher never signals a node that has not yet installed its traps, however busy the machine.
# fail prints a line after its error line a moment later, so the launcher reads them in separate chunks
# (the reason was lost then: 1 in ~10 runs under load printed "fail failed: stopping server").
name="$3"
echo "profile=$FASTDDS_DEFAULT_PROFILES_FILE"
echo -n "partial line without newline"; echo " completed"
wait_ready() { if [ -n "$READY" ]; then while [ ! -e "$READY" ]; do sleep 0.02; done; fi; }
ready() { if [ -n "$READY" ]; then touch "$READY"; fi; }
case "$name" in
  quick) wait_ready; sleep 0.2; echo "finished"; exit 0 ;;
  fail) wait_ready; sleep 0.2; echo "something broke" >&2; echo "[ERROR] [1795368386.5] [fail]: bag /x does not exist" >&2
        sleep 0.3; echo "later output"; exit 3 ;;
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
    assert "[quick ] finished" in text, text                     # output prefixed with the (padded) node name
    assert "[server] partial line without newline completed" in text, text
    assert "[server] got SIGINT" in text, text                   # the others were stopped with SIGINT
    assert "required node quick ended" in text and "all nodes ended cleanly" in text, text
    profile = str(graph.share_file("config", "fastdds_shm.xml"))
    assert f"[server] profile={profile}" in text, text
    assert not any(_alive(p) for p in _pids(text)), text


def test_a_node_that_ends_normally_does_not_end_the_graph(fake_python, tmp_path):
    out = SignalOn("quick exited with status 0")        # Ctrl-C once quick has ended
    rc = launcher.launch([NodeSpec("server", "server"), NodeSpec("quick", "quick")],
                         env={"PATH": os.environ["PATH"], "FASTDDS_DEFAULT_PROFILES_FILE": "/mine.xml",
                              "READY": str(tmp_path / "ready")}, out=out, python=fake_python)
    text = out.getvalue()
    # the server kept running after `quick` ended, until Ctrl-C, which it got once and obeyed
    assert rc == 0, text
    assert text.index("quick exited with status 0") < text.index("SIGINT received: stopping server"), text
    assert text.count("[server] got SIGINT") == 1, text
    assert "[server] profile=/mine.xml" in text, text            # a profile chosen by the caller is kept
    assert not any(_alive(p) for p in _pids(text)), text


def test_failing_node_stops_the_graph_with_an_error(fake_python, tmp_path):
    out = io.StringIO()
    rc = launcher.launch([NodeSpec("server", "server"), NodeSpec("fail", "fail")],
                         env={"PATH": os.environ["PATH"], "READY": str(tmp_path / "ready")}, out=out,
                         python=fake_python)
    text = out.getvalue()
    assert rc == 1, text
    assert "[fail  ] something broke" in text, text               # stderr is shown too
    assert "fail exited with status 3 (FAILED)" in text, text
    # the graph ends with the node's reason: its last error line
    assert "fail failed (bag /x does not exist): stopping server" in text, text
    assert "FAILED: fail (bag /x does not exist)" in text, text


def test_node_ignoring_signals_is_killed_and_reported(fake_python, tmp_path):
    out = io.StringIO()
    t0 = time.monotonic()
    rc = launcher.launch([NodeSpec("stubborn", "stubborn"), NodeSpec("quick", "quick", required=True)],
                         env={"PATH": os.environ["PATH"], "READY": str(tmp_path / "ready")}, out=out,
                         python=fake_python, stop_timeout=0.3)
    text = out.getvalue()
    assert rc == 1, text
    assert "sending SIGTERM" in text and "sending SIGKILL" in text and "killed by SIGKILL" in text, text
    assert time.monotonic() - t0 < 5, text
    assert not any(_alive(p) for p in _pids(text)), text


def test_repeated_ctrl_c_escalates_at_once(fake_python):
    # Ctrl-C once the node ignores signals, again once the launcher is stopping it, a third time after SIGTERM
    out = SignalOn("[stubborn] ignoring signals", "SIGINT received: stopping stubborn", "sending SIGTERM")
    t0 = time.monotonic()
    rc = launcher.launch([NodeSpec("stubborn", "stubborn")], env={"PATH": os.environ["PATH"]}, out=out,
                         python=fake_python, stop_timeout=60)
    text = out.getvalue()
    assert rc == 1 and "sending SIGTERM" in text and "sending SIGKILL" in text, text
    assert time.monotonic() - t0 < 10, text                      # not 2 x stop_timeout
    assert not any(_alive(p) for p in _pids(text)), text


def test_launch_rejects_bad_graphs():
    with pytest.raises(ValueError, match="empty"):
        launcher.launch([])
    with pytest.raises(ValueError, match="unique"):
        launcher.launch([NodeSpec("a", "x"), NodeSpec("b", "x")])


def test_cli_has_launch_and_play(capsys):
    from uw_sil.cli import build_parser

    args = build_parser().parse_args(["launch", "backward", "--bag", "t.mcap", "--frames", "2", "--optimizer",
                                      "cmaes", "--rate", "0.5", "--output-yaml", "f.yaml", "--keep-running"])
    assert args.func is launcher.cmd_launch and args.graph == "backward" and args.rate == 0.5
    assert args.frames == 2 and args.keep_running is True and args.loop is False and args.stride is None
    # every option of `uw-sil launch backward` is a launch argument of the graph, checked the same way
    for option, value in (("--frames", "abc"), ("--rate", "0"), ("--optimizer", "bogus"), ("--stride", "0")):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["launch", "backward", option, value])
        name = option[2:].replace("-", "_")
        assert f"argument {name}:='{value}' is not valid: expected" in capsys.readouterr().err
    args = build_parser().parse_args(["play", "t.mcap", "--loop", "--rate", "2"])
    assert args.func is launcher.cmd_play and args.loop and args.rate == 2.0
    with pytest.raises(SystemExit):
        build_parser().parse_args(["play", "t.mcap", "--rate", "0"])


# ------------------------------------------------------------------------------------------ graph arguments

BACKWARD = graph.GRAPHS["backward"]


def test_graph_arguments_parse_launch_text_and_name_the_argument():
    values = BACKWARD.parse({"frames": "5", "rate": "2.5", "keep_running": "True", "loop": "1", "bag": "b"})
    assert values["frames"] == 5 and values["rate"] == 2.5 and values["keep_running"] is True
    assert values["loop"] is True and values["bag"] == "b"
    assert values["optimizer"] == "pso" and values["stride"] is None and values["max_iter"] is None  # defaults
    for text, want in (("false", False), ("0", False), ("no", False), ("OFF", False), ("yes", True), ("on", True)):
        assert BACKWARD.parse({"keep_running": text})["keep_running"] is want
    for name, text, expected in (("frames", "abc", "an integer >= 1"), ("frames", "0", "an integer >= 1"),
                                 ("frames", "2.5", "an integer >= 1"), ("rate", "0", "a number > 0"),
                                 ("rate", "nan", "a number > 0"), ("keep_running", "maybe", "true or false"),
                                 ("optimizer", "bogus", "one of pso, cmaes"), ("max_iter", "-1", "an integer >= 1")):
        with pytest.raises(ValueError) as e:
            BACKWARD.parse({name: text})
        assert str(e.value) == f"argument {name}:={text!r} is not valid: expected {expected}"
    with pytest.raises(ValueError, match="frames.*rate"):          # every bad argument is named at once
        BACKWARD.parse({"frames": "x", "rate": "-1"})
    with pytest.raises(ValueError, match="no argument.*framez"):
        BACKWARD.parse({"framez": "3"})


def test_graph_arguments_describe_themselves():
    for a in BACKWARD.arguments:
        assert a.description and a.help.startswith(a.description)
        assert a.parse(a.default_text) == a.default          # the launch file's default text gives the default
    assert BACKWARD.argument("rate").help == "bag replay rate (2: twice as fast as recorded) (a number > 0; default 1.0)"
    with pytest.raises(KeyError, match="no argument"):
        BACKWARD.argument("nope")


@pytest.mark.parametrize("name", ["backward", "forward", "sil"])
def test_start_paused_replays_wait_for_resume(name):
    """start_paused:=true: bag_play waits for ~/resume; backward_fit does not give up on its first frame
    meanwhile (its first_frame_timeout would otherwise fail the fit while the user sets up a recorder)."""
    g = graph.GRAPHS[name]
    paused = {s.name: s for s in g.nodes({"bag": "/d/t.mcap", "start_paused": "true"})}
    plain = {s.name: s for s in g.nodes({"bag": "/d/t.mcap"})}
    assert paused["bag_play"].parameters["start_paused"] is True
    assert "start_paused" not in plain["bag_play"].parameters
    if "backward_fit" in paused:
        assert plain["backward_fit"].parameters["first_frame_timeout"] == graph.FIRST_FRAME_TIMEOUT > 0
        assert paused["backward_fit"].parameters["first_frame_timeout"] == 0.0


def test_graph_nodes_come_from_the_arguments():
    specs = BACKWARD.nodes({"bag": "/d/t.mcap", "max_iter": "7", "output_yaml": "/d/fit.yaml", "loop": "true"})
    want = graph.backward_graph(bag="/d/t.mcap", max_iter=7, output_yaml="/d/fit.yaml", loop=True)
    assert specs == want
    assert BACKWARD.nodes({}) == graph.backward_graph()         # no arguments: the builder's defaults


def test_failure_reason_is_the_last_error_a_node_printed():
    lines = ["[INFO] [1.0] [bag_play]: starting", "[ERROR] [1795368386.536] [bag_play]: bag /x does not exist",
             "[INFO] [2.0] [bag_play]: bye"]
    assert graph.failure_reason(lines) == "bag /x does not exist"
    tb = ["Traceback (most recent call last):", '  File "x.py", line 1, in <module>',
          "rclpy.exceptions.InvalidParameterValueException: Invalid parameter value (9.0) for parameter a_r"]
    assert graph.failure_reason(lines + tb) == tb[-1]
    assert graph.failure_reason(["[bag_play-3] [FATAL] [1.5] [bag_play]: out of memory"]) == "out of memory"
    assert graph.failure_reason(["all good", "[WARN] [1.0] [n]: hm"]) == ""


@pytest.mark.parametrize("name", sorted(graph.GRAPHS))
def test_each_graph_has_a_generated_launch_file(name):
    """launch/<graph>.launch.py is the graph's generated description (launchgen; run with the real launch tools
    in test_ros2_tools): its arguments and nodes cannot drift from `uw-sil launch <graph>`."""
    text = graph.share_file("launch", f"{name}.launch.py").read_text()
    assert "from uw_sil.nodes.launchgen import generate" in text and f'return generate("{name}")' in text
    g = graph.GRAPHS[name]
    assert g.name == name and len({a.name for a in g.arguments}) == len(g.arguments)
    for a in g.arguments:                  # each one documented in the launch file's usage line
        assert f"{a.name}:=" in text, a.name
