"""The bad-input corpus (test/bad_inputs/make_corpus.py): every case is refused with its one-line message and
leaves nothing behind, or is accepted; a cut-off bag is salvaged; bugs still show a traceback."""
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from bad_inputs import make_corpus as corpus
from bad_inputs.make_corpus import CASES, LIBRARY_CASES, build
from uw_sil.cli import EXIT_BAD_INPUT, main

ENV = {**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "osmesa")}


def test_corpus_is_large_and_names_are_unique():
    names = [c.name for c in CASES] + [c.name for c in LIBRARY_CASES]
    assert len(CASES) >= 30 and len(names) == len(set(names))
    assert sum(c.accepted for c in CASES) >= 10 and sum(not c.accepted for c in CASES) >= 25


def _error_line(err: str) -> str:
    """The one ``uw-sil: error:`` line: the last line; before it only the "fitting with" notice and warnings."""
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("uw-sil: error: ")]
    assert len(errors) == 1 and lines[-1] == errors[0], err
    assert all(line.startswith(("fitting with ", "warning: ")) for line in lines[:-1]), err
    return errors[0]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_cli_case(case, tmp_path, capsys):
    args = build(case, tmp_path)
    out_dir = tmp_path / case.name / "out"
    rc = main(args)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    if case.accepted:
        assert rc == 0, err
        assert re.search(case.message, out + err), out + err
        if args[0] == "fit":
            summary = json.loads((out_dir / "fit.json").read_text())
            assert (out_dir / "fit.yaml").is_file() and len(summary["params"]) == 7
    else:
        assert rc == EXIT_BAD_INPUT, out + err
        line = _error_line(err)
        assert re.search(case.message, line), line
        # the line names the input: a file of the case, or the option
        assert str(tmp_path / case.name) in line or line.startswith("uw-sil: error: --"), line
        assert not out_dir.exists() or not any(out_dir.iterdir()), sorted(out_dir.rglob("*"))


@pytest.mark.parametrize("case", LIBRARY_CASES, ids=lambda c: c.name)
def test_library_case(case):
    if case.message is None:
        assert case.check(case.call())
    else:
        with pytest.raises(ValueError, match=case.message):
            case.call()


@pytest.mark.parametrize("name, expected", [
    ("enc_bgr8", lambda raw: raw[:, :, ::-1]),
    ("enc_mono8", lambda raw: np.repeat(raw, 3, axis=2)),
    ("enc_rgba8", lambda raw: raw[:, :, :3]),
    ("row_padding", lambda raw: raw[:, : corpus.W * 3].reshape(corpus.H, corpus.W, 3)),
    ("is_bigendian", lambda raw: raw),
])
def test_accepted_encodings_give_the_recorded_pixels(tmp_path, name, expected):
    from uw_sil.bags import read_samples

    case = next(c for c in CASES if c.name == name)
    build(case, tmp_path)
    samples = list(read_samples(tmp_path / name / "bag"))
    assert len(samples) == 2
    for i, s in enumerate(samples):
        ch = {"enc_bgr8": 3, "enc_mono8": 1, "enc_rgba8": 4, "row_padding": 3, "is_bigendian": 3}[name]
        step = corpus.W * ch + (16 if name == "row_padding" else 0)
        data = np.random.default_rng(i).integers(0, 256, corpus.H * step, dtype=np.uint8)
        raw = data.reshape(corpus.H, step) if name == "row_padding" else data.reshape(corpus.H, corpus.W, ch)
        np.testing.assert_array_equal(s.image, expected(raw))


def test_truncated_bag_every_intact_frame_is_used_and_the_loss_reported(tmp_path, capsys):
    from uw_sil.bags import read_samples

    bag = corpus.truncated_mcap(tmp_path, keep=0.6)
    stream = read_samples(bag)
    got = list(stream)
    n = len(got)
    assert 0 < n < 6
    for i, s in enumerate(got):                      # the first n frames, pixel for pixel
        assert s.stamp_ns == corpus.T0 + i * corpus.DT
        np.testing.assert_array_equal(s.image, corpus.water_image(seed=i))
    assert stream.report.truncated and stream.report.lost == {t: 6 - n for t in (corpus.IMAGE, corpus.INFO, corpus.POSE)}
    # every intact frame is fitted (asking for all 6), and the loss is in the warning and the summary
    out = tmp_path / "out"
    assert main(["fit", "--bag", str(bag), "--frames", "6", "--optimizer", "cmaes", "--max-iter", "1",
                 "--out", str(out / "fit.yaml")]) == 0
    err = capsys.readouterr().err
    assert f"lost {{'{corpus.IMAGE}': {6 - n}," in err and "fitting the intact frames" in err
    summary = json.loads((out / "fit.json").read_text())
    assert [f["index"] for f in summary["frames"]] == list(range(n))
    assert summary["bag_damage"]["truncated"] and summary["bag_damage"]["lost"][corpus.IMAGE] == 6 - n


@pytest.mark.parametrize("name", ["params_not_a_number", "zero_length"])
def test_refusal_from_a_real_process_is_one_line(tmp_path, name):
    case = next(c for c in CASES if c.name == name)
    args = build(case, tmp_path)
    p = subprocess.run([sys.executable, "-m", "uw_sil.cli", *args], env=ENV, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == EXIT_BAD_INPUT, p.stderr
    assert re.search(case.message, _error_line(p.stderr)) and "Traceback" not in p.stderr
    assert p.stdout == ""


def test_a_bug_still_shows_a_traceback(tmp_path, monkeypatch):
    """Only known user errors become one line: anything else propagates (Python prints the traceback)."""
    import uw_sil.fit.backward as backward

    def broken(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(backward, "fit_bag", broken)
    bag = corpus.write_bag(tmp_path / "bag", corpus.frames(1))
    with pytest.raises(RuntimeError, match="a bug"):
        main(["fit", "--bag", str(bag), "--out", str(tmp_path / "fit.yaml")])
    assert not (tmp_path / "fit.yaml").exists()


def test_corpus_script_writes_the_cases_asked_for(tmp_path):
    """``make_corpus.py OUT CASE...`` run as a script generates one folder per case with its command line
    (every case's generation is exercised by test_cli_case; here a few, through the script)."""
    names = ["zero_length", "enc_bgr8", "params_yaml_malformed"]
    p = subprocess.run([sys.executable, corpus.__file__, str(tmp_path), *names], env=ENV, capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == f"3 cases in {tmp_path}"
    assert sorted(d.name for d in tmp_path.iterdir()) == sorted(names)
    for name in names:
        assert (tmp_path / name / "command.txt").read_text().startswith("uw-sil ")
    p = subprocess.run([sys.executable, corpus.__file__, str(tmp_path), "no_such_case"], env=ENV,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "unknown case(s): no_such_case" in p.stderr


@pytest.mark.parametrize("name, stamps", [
    ("stamps_out_of_order", [corpus.T0 + k * corpus.DT for k in (1, 0, 3, 2, 4)]),
    ("stamps_duplicated", [corpus.T0, corpus.T0 + corpus.DT, corpus.T0 + corpus.DT, corpus.T0 + 2 * corpus.DT]),
])
def test_out_of_order_and_duplicated_stamps_pair_each_image_exactly(tmp_path, name, stamps):
    from uw_sil.bags import read_samples

    build(next(c for c in CASES if c.name == name), tmp_path)
    stream = read_samples(tmp_path / name / "bag")
    got = list(stream)
    assert sorted(s.stamp_ns for s in got) == sorted(stamps)
    assert stream.report.sync.exact == len(stamps) and stream.report.sync.dropped == 0
    for s in got:                                   # its own image (frame i was drawn with seed i)
        i = next(i for i, t in enumerate(stamps) if t == s.stamp_ns and
                 np.array_equal(s.image, corpus.water_image(seed=i)))
        assert i is not None


def test_error_line_names_a_relative_bag_once(tmp_path, monkeypatch, capsys):
    """A relative bag name: the line starts with it (or its directory) once, also when the message starts with
    a word that begins like the name ("t.mcap" / "topic ...")."""
    monkeypatch.chdir(tmp_path)
    corpus.write_bag(tmp_path / "t", corpus.frames(1, topics=(corpus.INFO, corpus.POSE)))
    assert main(["fit", "--bag", "t.mcap", "--out", "out/fit.yaml"]) == EXIT_BAD_INPUT
    assert _error_line(capsys.readouterr().err) == (
        "uw-sil: error: t: topic '/camera/image_raw' is not in the bag; it has: /camera/camera_info "
        "[sensor_msgs/msg/CameraInfo], /panel/pose [geometry_msgs/msg/PoseStamped]")
    assert main(["synth", "--out", "t2.mcap", "--frames", "1", "--params", "t=1"]) == EXIT_BAD_INPUT
    assert _error_line(capsys.readouterr().err).startswith("uw-sil: error: --params: unknown parameter 't'")
