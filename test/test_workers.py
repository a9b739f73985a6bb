"""Worker processes (uw_sil._shared.workers): the same results as in one process, errors and Ctrl-C-like
interrupts reach the caller and stop the workers, a dead worker is named, the caller's script is never run
again in a worker, and a diagnosis gives the same document with one process or two."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from uw_sil._shared.workers import WorkerError, WorkerPool

HERE = Path(__file__).resolve().parent


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    """The workers import this module to find the functions below."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))


# ---------------------------------------------------------------- work (module level: the workers import it)

def scaled(shared, item):
    return shared * item


def where(shared, item):
    """(pid, id of the shared object in that process, the thread budget there)"""
    from uw_sil._shared.process import default_threads

    print("work that prints must not break the answers")
    return os.getpid(), id(shared), default_threads()


def fails(shared, item):
    if item == 2:
        raise KeyError(f"item {item}")
    return item


def slow(shared, item):
    time.sleep(30)
    return item


def package(shared, item):
    """Where the worker's uw_sil comes from."""
    import uw_sil

    return os.path.dirname(os.path.abspath(uw_sil.__file__))


def dies(shared, item):
    if item == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.5)
    return item


def _alive(pids) -> list:
    out = []
    for p in pids:
        try:
            os.kill(p, 0)
        except ProcessLookupError:
            continue
        out.append(p)
    return out


# ---------------------------------------------------------------- tests

def test_results_in_order_and_as_in_one_process():
    items = list(range(7))
    with WorkerPool(2) as pool:
        arrived = []
        got = pool.map(scaled, items, shared=3, done=lambda i, r: arrived.append(i),
                       cost=[1, 9, 2, 8, 3, 7, 4])
    assert got == [3 * i for i in items]
    assert sorted(arrived) == items
    with WorkerPool(1) as pool:
        assert pool.map(scaled, items, shared=3) == got


def test_work_runs_in_two_processes_with_one_thread_each_and_one_shared_copy():
    with WorkerPool(2) as pool:
        got = pool.map(where, range(8), shared=list(range(1000)))
        pids = {pid for pid, _, _ in got}
        assert len(pids) == 2 and os.getpid() not in pids
        for pid in pids:                      # the shared object came once to each worker
            assert len({sid for p, sid, _ in got if p == pid}) == 1
        assert {t for _, _, t in got} == {1}
    assert not _alive(pids), "workers outlived the pool"
    with WorkerPool(1) as pool:                # one process: the caller's
        assert {pid for pid, _, _ in pool.map(where, range(3))} == {os.getpid()}


def test_an_error_in_the_work_is_raised_here_with_the_worker_traceback():
    pool = WorkerPool(2)
    with pytest.raises(KeyError, match="item 2") as err:
        with pool:
            pool.map(fails, range(5))
    assert any("in a worker process" in n and "fails" in n for n in getattr(err.value, "__notes__", []))
    assert not pool._workers


def test_an_interrupt_stops_the_workers_at_once():
    pool = WorkerPool(2).start()
    pids = [w.proc.pid for w in pool._workers]
    t0 = time.monotonic()

    def interrupt():
        if time.monotonic() - t0 > 0.5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        pool.map(slow, range(4), interrupt=interrupt)
    assert time.monotonic() - t0 < 10.0, "the interrupt waited for the work"
    assert not _alive(pids), "workers still running after the interrupt"


def test_a_killed_worker_is_named():
    with pytest.raises(WorkerError, match=r"worker process \d+ ended without an answer \(exit code -9\)"):
        with WorkerPool(2) as pool:
            pool.map(dies, range(3))


def test_the_callers_script_is_not_run_again_in_the_workers(tmp_path):
    """A script without an ``if __name__ == "__main__"`` guard (multiprocessing's spawn would run it again in
    every worker, and start workers there in turn)."""
    script = tmp_path / "unguarded.py"
    script.write_text(textwrap.dedent("""
        from uw_sil._shared.workers import WorkerPool
        from test_workers import scaled
        print("script ran")
        with WorkerPool(2) as pool:
            print(pool.map(scaled, [1, 2, 3], shared=2))
    """))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ["PYTHONPATH"]])})
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["script ran", "[2, 4, 6]"]


def test_the_workers_run_the_callers_uw_sil_whatever_the_working_directory(tmp_path, monkeypatch):
    """``python -m`` and ``-c`` put the working directory first on the path: run from another checkout, the
    workers imported that one's uw_sil (a bench run there with this checkout's code on its PYTHONPATH refitted
    vignetting with the other checkout's four parameters, and the parent's five-parameter model failed)."""
    import uw_sil

    other = tmp_path / "uw_sil"
    other.mkdir()
    (other / "__init__.py").write_text("raise ImportError('the checkout in the working directory')\n")
    monkeypatch.chdir(tmp_path)
    with WorkerPool(2) as pool:
        got = pool.map(package, range(2))
    assert got == [os.path.dirname(os.path.abspath(uw_sil.__file__))] * 2


def test_a_diagnosis_is_the_same_with_one_process_or_two(tmp_path):
    """The candidates of a round refitted side by side in two worker processes give the document of the
    refits one after the other, bit for bit (only the times differ). (Until the seafloor's texture pyramid was
    built under a lock, a two-process diagnosis of a seafloor dive could differ from the one-process one, up to
    the effect named first: uw_sil.sim.effects.unmodeled_geometry, whose race has a test of its own.) Two
    effects judged on statistics are allowed, so that their judges run side by side too. The round's winner is
    refitted with the full budget in the diagnosis's own process, its θ evaluations shared out among the workers
    with two (:attr:`uw_sil.fit.judges.base.Job.pool`), on threads with one."""
    from uw_sil.bags.synth import synthesize_trial
    from uw_sil.fit.diagnose import diagnose_bag, without_times
    from uw_sil.sim.camera import CameraModel

    bag = tmp_path / "lamps.mcap"
    synthesize_trial(bag, n_frames=6, seed=5, camera=CameraModel.from_fov(160, 120),
                     effects={"artificial_light": "strong"})
    allowed = ["artificial_light", "vignetting", "camera_response", "sensor_noise", "compression"]

    def doc(processes):
        d = diagnose_bag(bag, k=6, max_effects=1, effects_allowed=allowed, processes=processes).to_json()
        return without_times(d)

    one, two = doc(1), doc(2)
    assert _largest_difference(one, two) == 0, _largest_difference(one, two, where=True)
    assert [s["chosen"] for s in one["selection"]] == [s["chosen"] for s in two["selection"]]
    assert any(c.get("round") == 1 for c in two["candidates"])
    assert any(c.get("full_refit") for c in two["candidates"])
    assert {"sensor_noise", "compression"} <= {c["effect"] for c in two["candidates"]}


def _largest_difference(a, b, path="", where=False):
    """The largest absolute difference of two documents' numbers (inf where their structure or any other
    value differs); ``where``: also the path of the first such place."""
    found = []

    def walk(x, y, p):
        if isinstance(x, dict) and isinstance(y, dict):
            if set(x) != set(y):
                found.append((float("inf"), p))
                return
            for k in x:
                walk(x[k], y[k], f"{p}.{k}")
        elif isinstance(x, list) and isinstance(y, list):
            if len(x) != len(y):
                found.append((float("inf"), p))
                return
            for i, (u, v) in enumerate(zip(x, y)):
                walk(u, v, f"{p}[{i}]")
        elif isinstance(x, (int, float)) and isinstance(y, (int, float)) and not isinstance(x, bool):
            found.append((abs(float(x) - float(y)), p))
        elif x != y:
            found.append((float("inf"), p))

    walk(a, b, path)
    worst = max(found, default=(0.0, ""))
    return worst if where else worst[0]
