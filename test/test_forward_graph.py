"""The forward and sil graphs: one description for `uw-sil launch forward|sil` and the launch files."""
import pytest

from uw_sil.nodes import graph, launcher


def test_forward_graph_with_a_bag_ends_with_the_enhancer():
    specs = {s.name: s for s in graph.forward_graph(sim_params="/d/fit.yaml", bag="/d/t.mcap", method="dcp")}
    assert list(specs) == ["sim_camera", "enhancer", "bag_play"]
    assert specs["sim_camera"].param_files == ["/d/fit.yaml"]
    # renders every replayed pose, and sends every render reliably to the enhancer, which reads reliably
    assert specs["sim_camera"].parameters == {**graph.REPLAY_SIM_CAMERA, "reliable_output": True}
    e = specs["enhancer"]
    assert e.required and e.parameters["idle_timeout"] == graph.IDLE_TIMEOUT and e.parameters["method"] == "dcp"
    assert e.parameters["reliable_input"] is True and e.parameters["queue_size"] == graph.REPLAY_ENHANCER_QUEUE
    play = specs["bag_play"].parameters
    assert play["wait_for_topics"] == ["/camera/image_raw", "/panel/pose"] and "wait_for_nodes" not in play
    assert not specs["bag_play"].required


@pytest.mark.parametrize("kwargs", [{}, {"bag": "/d/t.mcap", "keep_running": True}, {"bag": "/d/t.mcap", "loop": True}])
def test_live_or_looping_forward_graphs_run_until_stopped(kwargs):
    specs = graph.forward_graph(**kwargs)
    assert not any(s.required for s in specs)
    assert all("idle_timeout" not in s.parameters for s in specs)
    if "bag" not in kwargs:
        assert [s.name for s in specs] == ["sim_camera", "enhancer"] and specs[0].parameters == {}


def test_sil_graph_is_backward_plus_forward():
    specs = {s.name: s for s in graph.sil_graph(bag="/d/t.mcap", output_yaml="/d/fit.yaml", frames=2,
                                                optimizer="cmaes", b_from_frame=True)}
    assert list(specs) == ["sim_camera", "backward_fit", "enhancer", "bag_play"]
    assert specs["backward_fit"].required and specs["backward_fit"].parameters["output_yaml"] == "/d/fit.yaml"
    assert not specs["enhancer"].required and specs["enhancer"].parameters["b_from_frame"] is True
    assert specs["bag_play"].parameters["wait_for_nodes"] == ["backward_fit", "enhancer",
                                                             "sim_camera:/camera/camera_info"]
    backward = {s.name: s for s in graph.backward_graph(bag="/d/t.mcap", output_yaml="/d/fit.yaml", frames=2,
                                                        optimizer="cmaes")}
    assert specs["backward_fit"].parameters == backward["backward_fit"].parameters


def test_launch_command_passes_the_forward_options(monkeypatch):
    from uw_sil.cli import build_parser

    seen = []
    monkeypatch.setattr(launcher, "launch", lambda specs: seen.append(specs) or 0)
    args = build_parser().parse_args(["launch", "forward", "--bag", "t.mcap", "--method", "udcp", "--b-from-frame",
                                      "--sim-params", "fit.yaml"])
    assert args.func(args) == 0
    e = next(s for s in seen[0] if s.name == "enhancer")
    assert e.parameters["method"] == "udcp" and e.parameters["b_from_frame"] is True
    args = build_parser().parse_args(["launch", "backward", "--bag", "t.mcap"])    # takes no forward options
    assert args.func(args) == 0 and "enhancer" not in [s.name for s in seen[1]]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["launch", "forward", "--method", "clahe"])
