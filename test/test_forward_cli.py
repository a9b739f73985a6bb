"""`uw-sil enhance` and `uw-sil features` on a tiny synthetic trial: the output bag (readable, complete,
atomic), the Table-2 output (deterministic), the report, and bad input."""
import csv
import os
import subprocess
import sys

import numpy as np
import pytest

from uw_sil.bags import iter_messages, open_bag, read_samples
from uw_sil.bags.imgmsg import image_to_rgb
from uw_sil.cli import main
from uw_sil.enhance.sil import Enhancer, load_model_yaml
from uw_sil.fit.backward import write_params_yaml
from uw_sil.bags.synth import load_truth
from uw_sil.sim.render import Renderer

ENV = {**os.environ, "PYOPENGL_PLATFORM": "osmesa"}


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    d = tmp_path_factory.mktemp("fwd")
    assert main(["synth", "--out", str(d / "t.mcap"), "--frames", "6", "--width", "160", "--height", "120",
                 "--start", "2.5", "--end", "1.2", "--seed", "2"]) == 0
    truth = load_truth(d / "t.mcap")
    write_params_yaml(d / "fit.yaml", truth["params"], fog=truth["fog"])
    return d / "t.mcap", d / "fit.yaml"


def test_enhance_writes_a_bag_with_the_enhanced_topic_next_to_the_inputs(trial, tmp_path, capsys):
    bag, fit = trial
    out = tmp_path / "enh.mcap"
    assert main(["enhance", "--bag", str(bag), "--params", str(fit), "--out", str(out)]) == 0
    assert "for 6 of 6 frames" in capsys.readouterr().out
    info = open_bag(tmp_path / "enh")
    src = open_bag(bag)
    assert info.topics["/camera/image_enhanced"].count == 6
    for t, ti in src.topics.items():
        assert info.topics[t].count == ti.count and info.topics[t].msgtype == ti.msgtype
    assert list(tmp_path.iterdir()) == [tmp_path / "enh"]            # no temporary left beside it
    # the existing readers take it, and each enhanced frame is the library's SIL of its recorded frame
    samples = list(read_samples(tmp_path / "enh"))
    enhanced = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: (t, m)
                for t, m in iter_messages(tmp_path / "enh", "/camera/image_enhanced")}
    assert sorted(enhanced) == [s.stamp_ns for s in samples]
    e = Enhancer(load_model_yaml(fit))
    with Renderer(camera=samples[0].camera) as r:
        for s in samples[::2]:
            t, msg = enhanced[s.stamp_ns]
            assert t == s.stamp_ns                                      # stored at its frame's receive time
            assert msg.header.frame_id == s.frame_id
            want = e.enhance(s.image, geometry=r.render(s.pose)).image
            np.testing.assert_array_equal(image_to_rgb(msg), want)
    # the bag plays in time order
    times = [m.log_time_ns for m in __import__("uw_sil.bags", fromlist=["iter_raw"]).iter_raw(tmp_path / "enh")]
    assert times == sorted(times)


def test_enhance_dcp_needs_no_params_and_refuses_to_overwrite(trial, tmp_path, capsys):
    bag, fit = trial
    out = tmp_path / "d.mcap"
    assert main(["enhance", "--bag", str(bag), "--method", "udcp", "--out", str(out)]) == 0
    before = sorted(p.stat().st_mtime_ns for p in (tmp_path / "d").iterdir())
    assert main(["enhance", "--bag", str(bag), "--method", "dcp", "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert sorted(p.stat().st_mtime_ns for p in (tmp_path / "d").iterdir()) == before
    assert main(["enhance", "--bag", str(bag), "--method", "dcp", "--out", str(out), "--force"]) == 0


@pytest.mark.parametrize("params,message", [
    (None, "--params fit.yaml is required"),
    ("missing.yaml", "does not exist"),
    ("bad.yaml", "not valid YAML"),
    ("short.yaml", "lacks"),
])
def test_enhance_bad_params_are_clear_errors_and_write_nothing(trial, tmp_path, capsys, params, message):
    bag, _ = trial
    (tmp_path / "bad.yaml").write_text("/**: {ros__parameters: [1, 2\n")
    (tmp_path / "short.yaml").write_text("/**:\n  ros__parameters:\n    a_r: 0.4\n")
    args = ["enhance", "--bag", str(bag), "--out", str(tmp_path / "o.mcap")]
    if params:
        args += ["--params", str(tmp_path / params)]
    assert main(args) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_enhance_of_a_bag_without_images_is_a_clear_error(trial, tmp_path, capsys):
    bag, fit = trial
    assert main(["enhance", "--bag", str(tmp_path / "none.mcap"), "--params", str(fit), "--out",
                 str(tmp_path / "o.mcap")]) == 2
    assert "error" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_ctrl_c_during_enhance_leaves_nothing(trial, tmp_path):
    """SIGINT while frames are being enhanced: exit 130 and no output bag nor temporary directory."""
    bag, fit = trial
    code = ("import signal, threading, os, uw_sil.enhance.bagtool as b\n"
            "orig = b.Enhancer.enhance\n"
            "def slow(self, *a, **k):\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    return orig(self, *a, **k)\n"
            "b.Enhancer.enhance = slow\n"
            "from uw_sil.cli import main\n"
            f"raise SystemExit(main(['enhance', '--bag', {str(bag)!r}, '--params', {str(fit)!r}, '--out', "
            f"{str(tmp_path / 'o.mcap')!r}]))\n")
    out = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True, timeout=120)
    assert out.returncode == 130, out.stderr
    assert list(tmp_path.iterdir()) == []


def test_features_prints_table_writes_csv_and_report_deterministically(trial, tmp_path, capsys):
    bag, fit = trial
    args = ["features", "--bag", str(bag), "--params", str(fit), "--frames", "3,5"]
    assert main(args + ["--csv", str(tmp_path / "a.csv"), "--report", str(tmp_path / "rep")]) == 0
    text = capsys.readouterr().out
    assert "| pair | ORB | BRIEF | SIFT | SURF | KAZE | AKAZE |" in text
    for label in ("| raw |", "| DCP |", "| UDCP |", "| SIL |"):
        assert label in text
    assert "SIL has more verified matches than DCP for" in text
    assert "PSNR" in text                                       # synthetic: quality against the truth
    assert main(args + ["--csv", str(tmp_path / "b.csv")]) == 0
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()
    rows = list(csv.DictReader(open(tmp_path / "a.csv")))
    assert len(rows) == 24 and {r["pair"] for r in rows} == {"raw", "DCP", "UDCP", "SIL"}
    for f in ("fig4_enhancement.png", "fig5_matches.png", "forward.html", "features.csv", "quality.csv"):
        assert (tmp_path / "rep" / f).stat().st_size > 0, f
    quality = list(csv.DictReader(open(tmp_path / "rep" / "quality.csv")))
    by = {(int(r["frame"]), r["method"]): float(r["psnr_db"]) for r in quality}
    for i in (3, 5):
        assert by[(i, "SIL")] > max(by[(i, "DCP")], by[(i, "UDCP")], by[(i, "raw")]) + 10


@pytest.mark.parametrize("frames,message", [("3", "two frame numbers"), ("2,2", "two different"),
                                            ("1,99", "no frame")])
def test_features_bad_frames(trial, capsys, frames, message):
    bag, fit = trial
    assert main(["features", "--bag", str(bag), "--params", str(fit), "--frames", frames]) == 2
    assert message in capsys.readouterr().err
