"""The `uw-sil` command as a user runs it: synth -> fit -> report, bad input, Ctrl-C."""
import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest
import yaml

from uw_sil.cli import main

ENV = {**os.environ, "PYOPENGL_PLATFORM": "osmesa"}


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    assert main(["synth", "--out", str(d / "t.mcap"), "--frames", "6", "--width", "160", "--height", "120",
                 "--params", "a_r=0.45,a_g=0.15,a_b=0.1,b_r=0.05,b_g=0.3,b_b=0.4,rho_f=0.1",
                 "--contact-sheet", str(d / "sheet.png")]) == 0
    return d / "t.mcap"


def test_synth_writes_bag_truth_and_contact_sheet(bag):
    assert (bag.parent / "t" / "metadata.yaml").exists()
    truth = json.loads((bag.parent / "t.truth.json").read_text())
    assert truth["params"]["a_r"] == 0.45 and truth["n_frames"] == 6
    assert (bag.parent / "sheet.png").stat().st_size > 10_000


def test_fit_writes_params_summary_and_report(bag, tmp_path, capsys):
    out = tmp_path / "fit.yaml"
    rc = main(["fit", "--bag", str(bag), "--frames", "2", "--stride", "3", "--optimizer", "cmaes", "--max-iter", "3",
               "--out", str(out), "--report", str(tmp_path / "report")])
    assert rc == 0
    params = yaml.safe_load(out.read_text())["/**"]["ros__parameters"]
    assert set(params) == {"a_r", "a_g", "a_b", "b_r", "b_g", "b_b", "rho_f", "fog_mode", "noise_sigma"}
    assert 0.5 < params["noise_sigma"] < 5.0            # the synthetic camera's 1-3 grey levels, estimated
    summary = json.loads((tmp_path / "fit.json").read_text())
    assert summary["optimizer"] == "cmaes" and summary["evaluations"] == 4 * 20
    assert len(summary["history_best_theta"]) == 4
    # never worse than where the optimizer started (the linear start), which beats the centre of the bounds
    assert summary["theta_after"] >= summary["theta_optimizer_start"] > summary["theta_before"]
    assert summary["stop_reason"] == "max_iter" and summary["patience"] > 0 and summary["tol"] > 0
    assert [f["index"] for f in summary["frames"]] == [0, 3]
    for name in ("index.html", "progression.png", "convergence.png", "residual.png"):
        assert (tmp_path / "report" / name).stat().st_size > 1000
    assert "ground truth" in (tmp_path / "report" / "index.html").read_text()
    # stop on convergence: nothing gains more than 1 in θ, so the fit ends after --patience iterations
    assert main(["fit", "--bag", str(bag), "--frames", "2", "--stride", "3", "--optimizer", "cmaes", "--tol", "1",
                 "--patience", "2", "--out", str(tmp_path / "conv.yaml")]) == 0
    conv = json.loads((tmp_path / "conv.json").read_text())
    assert conv["stop_reason"] == "converged" and conv["iterations"] == 2 and conv["evaluations"] == 3 * 20
    assert (conv["tol"], conv["patience"]) == (1.0, 2) and "stop: converged" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--frames", "0"], "must be >= 1"),
    (["--color-model", "hsv", "--sim-noise", "loud"], "--sim-noise: must be"),
])
def test_fit_bad_arguments_are_clear_errors(bag, tmp_path, capsys, args, message):
    assert main(["fit", "--bag", str(bag), "--out", str(tmp_path / "f.yaml"), *args]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "f.yaml").exists()


def test_bag_without_poses_is_a_clear_error(tmp_path, capsys):
    from uw_sil.bags import Sample, write_trial
    from uw_sil.sim.camera import CameraModel

    cam = CameraModel.from_fov(32, 24)
    write_trial(tmp_path / "np.mcap", [Sample(1, np.zeros((24, 32, 3), np.uint8), cam, np.eye(4))],
                pose_topic="/other/pose")
    assert main(["fit", "--bag", str(tmp_path / "np.mcap"), "--out", str(tmp_path / "f.yaml")]) == 2
    err = capsys.readouterr().err
    assert "/panel/pose" in err and "/other/pose" in err


def test_ctrl_c_during_fit_leaves_no_output(tmp_path):
    bag = tmp_path / "in" / "big.mcap"
    assert main(["synth", "--out", str(bag), "--frames", "3", "--width", "320", "--height", "240"]) == 0
    out_dir = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "uw_sil.cli", "fit", "--bag", str(bag), "--optimizer", "pso",
                          "--start", "centre", "--out", str(out_dir / "fit.yaml"), "--report", str(out_dir / "report")],
                         env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # Ctrl-C once the optimizer runs: on its first progress line (3 frames x 2020 evaluations to go), not
    # after a fixed sleep that a busy machine may not have spent inside the fit
    seen = []
    while not (seen and seen[-1].startswith("pso: 1/101 it")):
        seen.append(p.stderr.readline())
        assert seen[-1], f"uw-sil fit ended before its first iteration: {seen}"
    assert any("fitting with pso" in line for line in seen), seen
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "interrupted" in err
    assert not out_dir.exists() or sorted(os.listdir(out_dir)) == []


def test_demo_says_what_was_found_and_what_else_was_named():
    from uw_sil.cli import found_words

    assert found_words(["artificial_light"], ["artificial_light"]) == "found"
    assert found_words(["artificial_light"], ["backscatter_coefficient", "artificial_light"]) == \
        "found (also named, not concealed: backscatter_coefficient)"
    assert found_words(["artificial_light", "vignetting"], ["vignetting"]) == "NOT found: artificial_light"
    assert found_words([], ["vignetting"]) == "nothing concealed (also named, not concealed: vignetting)"
