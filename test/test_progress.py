"""Progress display: a carriage-return bar only on a terminal; whole, rate-limited lines in logs and pipes."""
import io
import os
import subprocess
import sys

import numpy as np

from uw_sil._shared.progress import LineProgress, progress_bar


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_log_lines_are_whole_and_rate_limited():
    out, clock = io.StringIO(), Clock()
    bar = LineProgress(10, "cmaes", unit="it", file=out, interval=5.0, clock=clock)
    bar.set_postfix(best="0.90000", evals=20)
    bar.update()                       # the first update is written at once
    for _ in range(3):                 # within 5 s: nothing
        clock.t += 1.0
        bar.update()
    clock.t += 2.5                     # 5.5 s after the first line
    bar.update()
    bar.close()                        # nothing new since the last line: no repeat
    bar.close()
    assert out.getvalue() == ("cmaes: 1/10 it (10%) best=0.90000 evals=20 0 s\n"
                              "cmaes: 5/10 it (50%) best=0.90000 evals=20 6 s\n")
    assert "\r" not in out.getvalue()


def test_close_writes_the_final_state_once():
    out, clock = io.StringIO(), Clock()
    with LineProgress(3, "render", unit="frame", file=out, clock=clock) as bar:
        bar.update()
        bar.update(2)
    assert out.getvalue().splitlines() == ["render: 1/3 frame (33%) 0 s", "render: 3/3 frame (100%) 0 s"]
    unknown = io.StringIO()
    with LineProgress(None, "scan", file=unknown, clock=clock) as bar:
        bar.update(7)
    assert unknown.getvalue() == "scan: 7 it 0 s\n"


def test_a_terminal_gets_the_tqdm_bar_and_anything_else_lines():
    from tqdm import tqdm

    tty = Terminal()
    bar = progress_bar(4, "pso", file=tty)
    assert isinstance(bar, tqdm)
    bar.update(4)
    bar.close()
    assert "\r" in tty.getvalue()
    assert isinstance(progress_bar(4, "pso", file=io.StringIO()), LineProgress)

    class Closed:                      # isatty() raising (a closed stream) counts as "not a terminal"
        def isatty(self):
            raise ValueError("I/O operation on closed file")
    assert isinstance(progress_bar(4, "pso", file=Closed()), LineProgress)


def test_optimizer_progress_in_a_log_has_no_carriage_returns(capsys):
    from uw_sil.fit.optimize import optimize

    optimize(lambda X: -np.sum((X - 0.3) ** 2, axis=1), [0, 0], [1, 1], method="cmaes", max_iter=3, seed=0,
             progress=True)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    assert lines[0].startswith("cmaes: 1/4 it (25%) best=") and lines[-1].startswith("cmaes: 4/4 it (100%)")


def test_cli_render_progress_through_a_pipe(tmp_path):
    """`uw-sil synth` in a pipe: whole lines on stderr (tqdm's bar used to disappear there)."""
    p = subprocess.run([sys.executable, "-m", "uw_sil.cli", "synth", "--out", str(tmp_path / "t.mcap"), "--frames",
                        "2", "--width", "32", "--height", "24"], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "osmesa")})
    assert p.returncode == 0, p.stderr
    assert "\r" not in p.stderr
    lines = [line.rsplit(" ", 2)[0] for line in p.stderr.splitlines() if line.startswith("render: ")]
    assert lines == ["render: 1/2 frame (50%)", "render: 2/2 frame (100%)"], p.stderr
