"""Faults over DDS, with the real nodes as separate processes (started as `uw-sil launch` starts them):
repeated SIGINT/SIGTERM stop every node and `uw-sil launch` cleanly within 5 s; SIGKILL of backward_fit
in the middle of a fit loses nothing (sim_camera keeps its parameters, the parameters file is the old one
or the new one, never half) and the graph restarts; shared-memory segments of killed processes do not
pile up in /dev/shm. (The enhancer's fault test joins once that node exists.)"""
import fcntl
import os
import re
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
import yaml

from conftest import import_or_skip  # noqa: E402  (skips locally, fails in CI when rclpy is missing)

rclpy = import_or_skip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")

pytestmark = pytest.mark.filterwarnings("ignore:module 'sre_:DeprecationWarning")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile  # noqa: E402
from std_msgs.msg import Float64, String  # noqa: E402

from uw_sil.bags.synth import synthesize_trial  # noqa: E402
from uw_sil.fit.backward import write_params_yaml  # noqa: E402
from uw_sil.nodes import clean_stale_shm_segments  # noqa: E402
from uw_sil.nodes.graph import backward_graph, command_line  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.sim.params import RGB_NAMES, UnderwaterParams  # noqa: E402

from rosproc import (Proc, assert_clean_output, domain_id, group_pids, logs, logs_on_failure, ros_env,  # noqa: E402
                     spin_until)

SMALL = CameraModel.from_fov(160, 120, 70.0)
START = 120.0          # generous: node start-up takes 3-10 s on a loaded 2-core machine
STOP = 5.0             # every node and the launcher must be gone this long after the signals


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    out = tmp_path_factory.mktemp("trial") / "trial.mcap"
    synthesize_trial(out, n_frames=12, seed=3, camera=SMALL, start_m=3.0, end_m=1.2)
    return out


@pytest.fixture(scope="module")
def sim_params(tmp_path_factory):
    """sim_camera's start-up parameters: small images and a known parameter set A."""
    f = tmp_path_factory.mktemp("params") / "sim.yaml"
    values = UnderwaterParams(a=(0.3, 0.1, 0.05), b=(0.1, 0.3, 0.4), rho_f=0.05).as_dict()
    f.write_text(yaml.safe_dump({"/**": {"ros__parameters": {**values, "fog_mode": "exp2", "noise_sigma": 0.0,
                                                               "width": SMALL.width, "height": SMALL.height}}}))
    return f, values


def _start(specs, domain, names=None) -> dict:
    """Each node of ``specs`` (or those named) as its own process group, as `uw-sil launch` runs them."""
    env = ros_env(domain)
    return {s.name: Proc(command_line(s), env, name=s.name) for s in specs if names is None or s.name in names}


READY = {"sim_camera": r"\[sim_camera\]: ready", "backward_fit": r"\[backward_fit\]: collecting \d+ frames",
         "bag_play": r"\[bag_play\]: .* playing at rate"}
#: The looping graph is running: bag_play has played the bag once and backward_fit has its frames and fits.
RUNNING = {"bag_play": r"\[bag_play\]: end of bag after \d+ messages: looping",
           "backward_fit": r"\[backward_fit\]: fitting \d+ frames"}
#: Between the two signals of a "repeated" pair: the second comes while the node handles the first, as a
#: terminal's Ctrl-C followed by the one launch forwards (the scenario's stimulus, not a synchronisation).
SECOND_SIGNAL_AFTER = 0.1


def _stop_all(procs):
    for p in procs.values():
        p.stop()


@pytest.mark.slow
@pytest.mark.parametrize("signals", [(signal.SIGINT, signal.SIGINT), (signal.SIGTERM, signal.SIGTERM),
                                     (signal.SIGINT, signal.SIGTERM)], ids=["INT-INT", "TERM-TERM", "INT-TERM"])
def test_every_node_stops_cleanly_on_repeated_signals(trial, sim_params, signals):
    """A terminal's Ctrl-C reaches a node and launch forwards another; SIGTERM likewise. Each node ends
    with status 0 within 5 s, without a traceback (a KeyboardInterrupt inside destroy_node, renderer
    close) or a crash."""
    specs = backward_graph(sim_params=str(sim_params[0]), bag=str(trial), loop=True, keep_running=True)
    procs = _start(specs, domain_id())
    try:
        with logs_on_failure(procs):
            for name, p in procs.items():
                p.wait_for(READY[name], timeout=START)
            for name, pattern in RUNNING.items():   # running: bag_play looping, backward_fit fitting its frames
                procs[name].wait_for(pattern, timeout=START)
            for p in procs.values():
                p.signal(signals[0])
            time.sleep(SECOND_SIGNAL_AFTER)
            for p in procs.values():
                p.signal(signals[1])
            for name, p in procs.items():
                took = p.wait_group(STOP)
                assert p.popen.returncode == 0, f"{name} exited with {p.popen.returncode}"
                assert_clean_output(p.text, name)
                assert took < STOP
    finally:
        _stop_all(procs)


#: A node started so, printing "importing" once the import of its module has begun (a meta-path finder
#: is asked for it first): a signal sent when the line appears comes during the import, however busy the
#: machine (a line printed before the import, and a fixed pause, raced the stop-signal handlers).
IMPORTING_NODE = """import sys


class Announce:
    def find_spec(self, name, path=None, target=None):
        if name == "uw_sil.nodes.backward_fit":
            print("importing", flush=True)
        return None


sys.meta_path.insert(0, Announce())
from uw_sil.nodes import entry
sys.exit(entry.backward_fit())
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["INT", "TERM"])
def test_a_node_stopped_while_it_imports_ends_cleanly(sig):
    """When one node fails, ``ros2 launch`` stops the others, and one may still be importing (rclpy, scipy,
    the renderer: about 1 s here, more under load). A SIGINT inside that import printed a KeyboardInterrupt
    traceback and the node died with -2 (seen in CI); it must end like a node stopped while running."""
    _stopped_before_it_started(IMPORTING_NODE, "importing", sig, STOP,
                               "the node had started: the signal did not come during the import")


def _stopped_before_it_started(script: str, ready: str, sig, within: float, started: str):
    """Run ``script`` (a backward_fit executable), wait for its line ``ready``, send ``sig`` (None: the script
    signals itself), and check that it ended within ``within`` s with exit code 0, printing nothing, the node never
    started (``started``: the message if it did)."""
    p = Proc([sys.executable, "-c", script], ros_env(domain_id()), name="backward_fit")
    try:
        with logs_on_failure(p):
            p.wait_for(ready, timeout=START)
            if sig is not None:
                p.signal(sig)
            assert p.wait_group(within) < within
            assert p.popen.returncode == 0
            assert_clean_output(p.text, "backward_fit")
            assert "[backward_fit]" not in p.text, started
    finally:
        p.stop()


SWALLOWED_STOP_NODE = """import os, signal, sys, weakref


class Stop:
    pass


class SwallowTheStop:
    def find_spec(self, name, path=None, target=None):
        if name == "uw_sil.nodes.backward_fit":
            def callback(_ref):
                os.kill(os.getpid(), signal.{sig})
                for _ in range(100000):      # the handler runs here: its KeyboardInterrupt is reported, not raised
                    pass
            obj = Stop()
            ref = weakref.ref(obj, callback)
            del obj
            print("signalled inside a weakref callback", flush=True)
        return None


sys.meta_path.insert(0, SwallowTheStop())
from uw_sil.nodes import entry
sys.exit(entry.backward_fit())
"""


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_stop_signal_swallowed_during_the_import_still_stops_the_node(sig):
    """A stop signal whose KeyboardInterrupt lands in a weakref callback of the import machinery (seen: a loaded
    test run, ``_get_module_lock.<locals>.cb``) is reported by the interpreter, not raised: the import went on,
    the node started and ran until killed. The signal was noted, so the node must not start: exit 0, nothing
    printed, no ``[backward_fit]`` log line."""
    _stopped_before_it_started(SWALLOWED_STOP_NODE.format(sig=sig), "signalled inside a weakref callback", None,
                               START, "the node started after the stop signal")


CTRL_C_LOOP = """
import os, signal, sys, threading
import rclpy
import uw_sil.nodes as un

def stop_once(i):
    un._handle_stop_signals()
    rclpy.init()
    node = rclpy.create_node(f"stopped_{{i}}")
    try:
        with un.executor_for(node) as executor:
            threading.Timer(0.002, os.kill, (os.getpid(), signal.SIGINT)).start()
            while True:
                executor.spin_once(timeout_sec=0.001)
    except KeyboardInterrupt:
        pass
    if signal.getsignal(signal.SIGINT) != signal.SIG_IGN or rclpy.ok():
        return 3
    un._settle_signals(rclpy)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0

ends = []
for i in range({n}):
    pid = os.fork()            # a node process of its own each time (rclpy and the package imported once)
    if pid == 0:
        code = stop_once(i)
        sys.stderr.flush()
        os._exit(code)
    ends.append(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]))
print("exit codes", sorted(set(ends)), "crashed", sum(e < 0 for e in ends), "of", len(ends), flush=True)
"""


def test_ctrl_c_while_spinning_never_crashes_the_clean_up():
    """Ctrl-C reaches rclpy's signal thread (it wakes the executors' guard conditions, then shuts the context
    down) while the main thread, interrupted, shuts its executor down and destroys the node. Destroying
    before that thread is done crashed (SIGSEGV: once in CI in ``destroy_publisher``; in this loop without
    the wait, about 1 in 100 stops; shutting the executor down first, 3 in 1450 stops of a publishing
    process). The clean-up of :func:`uw_sil.nodes.executor_for` and ``run_node`` lets the thread finish and
    ends it first: 100 stops in a row, each its own process, must all end cleanly."""
    done = subprocess.run([sys.executable, "-X", "faulthandler", "-c", CTRL_C_LOOP.format(n=100)],
                          capture_output=True, text=True, timeout=300, env=ros_env(domain_id()))
    assert done.returncode == 0 and "exit codes [0] crashed 0 of 100" in done.stdout, (
        done.returncode, done.stdout[-2000:], done.stderr[-4000:])


SIGNALS_DURING_CLEAN_UP = """
import os, signal, sys, time
import rclpy
import uw_sil.nodes as un

def quiet(*_):
    pass

def stopped_node(ready, hook):
    if hook:
        un._pass_over_stop_debris()      # what run_node installs in a node executable
    signal.signal(signal.SIGINT, quiet)          # a Python handler, as the nodes have (rclpy chains to it)
    rclpy.init()
    os.write(ready, b"r")
    deadline = time.monotonic() + 5
    while rclpy.ok() and time.monotonic() < deadline:   # the first SIGINTs shut rclpy down
        time.sleep(0.0005)
    un._stop_signals[:] = [signal.SIGINT]
    un._settle_signals(rclpy)                    # ignores SIGINT, takes rclpy's handlers out: SIGINTs keep coming
    for _ in range(1000):
        pass                                     # a signal tripped while being ignored is reported here
    return 0

ends = []
for i in range({n}):
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        code = stopped_node(w, {hook})
        sys.stderr.flush()
        os._exit(code)
    os.close(w)
    os.read(r, 1)
    os.close(r)
    while True:                                  # SIGINT after SIGINT until the process has ended
        try:
            os.kill(pid, signal.SIGINT)
        except ProcessLookupError:
            break
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            ends.append(os.waitstatus_to_exitcode(status))
            break
print("exit codes", sorted(set(ends)), "of", len(ends), flush=True)
"""


def test_signals_arriving_all_through_the_clean_up_print_nothing():
    """``ros2 launch`` forwards a second SIGINT after the terminal's. One that arrives while SIGINT is being
    set to SIG_IGN (here, or for an instant inside rclpy's ``uninstall_signal_handlers``) is reported by
    CPython as ``OSError: Signal 2 ignored due to race condition``, a traceback in the log of a node that
    ended cleanly (a graph test failed on it, once in eight loaded runs). 400 stopped processes, each sent
    SIGINT after SIGINT by their parent until they end, print nothing with the nodes' unraisable hook; the
    control without it shows that the race is reached (4-18 reports in 300 stops here, on a loaded machine):
    up to five batches of 400 are run until one is; if none is, the test warns that it tested nothing."""
    def stops(hook: bool) -> str:
        done = subprocess.run([sys.executable, "-c", SIGNALS_DURING_CLEAN_UP.format(n=400, hook=hook)],
                              capture_output=True, text=True, timeout=300, env=ros_env(domain_id()))
        assert done.returncode == 0 and "exit codes [0] of 400" in done.stdout, (done.stdout, done.stderr[-3000:])
        return done.stderr

    hooked = stops(True)
    assert "Traceback" not in hooked and "ignored due to race condition" not in hooked, hooked[-3000:]
    if not any("Signal 2 ignored due to race condition" in stops(False) for _ in range(5)):
        warnings.warn("2000 stops without the hook never reached the race: this run did not test the hook")


STOP_DEBRIS = """
import sys
import uw_sil.nodes as un
from rclpy.task import Task
un._pass_over_stop_debris()
if "{when}" == "stopped":
    un._stop_signals.append(2)
half = object.__new__(Task)          # what a KeyboardInterrupt inside Task.__init__ leaves behind
del half
if "{what}" == "interrupt":            # the second SIGINT landing in a generator closed by the first one's unwinding
    def reader():
        try:
            yield 1
        finally:
            raise KeyboardInterrupt
    stream = reader()
    next(stream)
    del stream
if "{what}" == "other":
    class Broken:
        def __del__(self):
            raise ValueError("a real error in a finalizer")
    broken = Broken()
    del broken
print("ended", flush=True)
"""


@pytest.mark.parametrize("when,what,printed", [
    ("stopped", "half", None),                                           # the stop's own debris: not printed
    ("running", "half", "no attribute '_exception'"),                    # without a stop: an error, printed
    ("stopped", "other", "a real error in a finalizer"),                 # any other finalizer error: printed
    ("stopped", "interrupt", None),                                      # our handler's in a finalizer: not
    ("running", "interrupt", "KeyboardInterrupt"),                       # ... unless no stop signal came
], ids=["stopped", "no-stop", "other-error", "interrupt-stopped", "interrupt-no-stop"])
def test_the_stop_signals_debris_in_finalizers_is_not_reported(when, what, printed):
    """Ctrl-C landing inside rclpy's ``Task`` constructor leaves a half-built future whose ``__del__`` fails
    (seen in ``backward_fit``'s log in a fresh-clone run: a traceback in an otherwise clean stop); a second
    Ctrl-C landing in a generator's ``finally`` while the first one unwinds raises KeyboardInterrupt in a
    finalizer (``bag_play``, a CI run). After a stop
    signal exactly that error is passed over; before one, or any other, is printed as usual."""
    done = subprocess.run([sys.executable, "-c", STOP_DEBRIS.format(when=when, what=what)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "ended" in done.stdout, done
    if printed is None:
        assert "Exception ignored" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    else:
        assert "Exception ignored" in done.stderr and printed in done.stderr, done.stderr


STUCK_TEARDOWN = """
import re, time
from uw_sil.nodes import teardown_deadline
with teardown_deadline({deadline}, armed={armed}):
    {body}
time.sleep({after})
print("ended", flush=True)
"""


@pytest.mark.parametrize("case", [
    # a C call holding the GIL past the deadline (catastrophic regex backtracking: minutes; the middleware's
    # participant deletion did this to sim_camera once): stacks on stderr, exit code 1
    dict(deadline=1.0, armed=True, body="re.match(r'(a+)+b', 'a' * 34)", after=0, code=1, dumped=True),
    # a teardown that ends in time: the timer is cancelled (the sleep after it outlasts the deadline)
    dict(deadline=1.0, armed=True, body="pass", after=2.0, code=0, dumped=False),
    # not armed (a node run inside a test): nothing ends the process
    dict(deadline=0.2, armed=False, body="time.sleep(1.0)", after=0, code=0, dumped=False),
], ids=["stuck", "in-time", "unarmed"])
def test_a_stuck_teardown_ends_the_process_with_its_stacks(case):
    """A node process whose teardown never returns (rclpy's ``destroy_node`` spinning inside the middleware
    with the GIL held) must still end: past the deadline the stacks go to stderr and the exit code is 1."""
    code = STUCK_TEARDOWN.format(**{k: case[k] for k in ("deadline", "armed", "body", "after")})
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == case["code"], done
    assert ("Timeout (0:00:01)!" in done.stderr) == case["dumped"], done.stderr
    assert ("ended" in done.stdout) == (not case["dumped"]), done
    if case["dumped"]:
        assert re.search(r'File "<string>", line 5 in <module>', done.stderr), done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("signals", [(signal.SIGINT, signal.SIGINT), (signal.SIGTERM, signal.SIGTERM)],
                         ids=["INT-INT", "TERM-TERM"])
def test_uw_sil_launch_stops_cleanly_on_repeated_signals(trial, sim_params, signals):
    cmd = [sys.executable, "-m", "uw_sil.cli", "launch", "backward", "--bag", str(trial), "--loop", "--keep-running",
           "--sim-params", str(sim_params[0]), "--optimizer", "cmaes", "--max-iter", "3"]
    launch = Proc(cmd, ros_env(domain_id()), name="uw-sil launch")
    try:
        with logs_on_failure(launch):
            for pattern in READY.values():     # node lines are prefixed "[name] ", then the node's own log line
                launch.wait_for(pattern, timeout=START)
            for pattern in RUNNING.values():
                launch.wait_for(pattern, timeout=START)
            launch.signal(signals[0])
            time.sleep(SECOND_SIGNAL_AFTER)
            launch.signal(signals[1])
            took = launch.wait_group(STOP)
            text = launch.text
            assert launch.popen.returncode == 0
            assert "all nodes ended cleanly" in text and "sending SIGKILL" not in text
            assert_clean_output(text, "uw-sil launch")
            pids = [int(line.split("(pid ")[1].split(")")[0]) for line in launch.lines if "(pid " in line]
            assert len(pids) == 3 and not any(Path(f"/proc/{pid}").exists() for pid in pids)
            assert took < STOP
    finally:
        launch.stop()


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["INT", "TERM"])
def test_backward_fit_stops_cleanly_while_waiting_for_sim_camera(trial, sig):
    """After the fit the node waits (up to 10 s) for sim_camera's parameter services in its fit thread;
    a signal then destroyed the client under the thread: a traceback from the thread."""
    specs = backward_graph(bag=str(trial), frames=2, stride=4, optimizer="cmaes", max_iter=2, keep_running=True)
    for s in specs:
        if s.name == "bag_play":                # no sim_camera here: the replay must not wait for it
            s.parameters["wait_for_nodes"] = ["backward_fit"]
    procs = _start(specs, domain_id(), names={"backward_fit", "bag_play"})     # no sim_camera
    try:
        with logs_on_failure(procs):
            fit = procs["backward_fit"]
            fit.wait_for(r"setting the parameters of sim_camera", timeout=START)
            fit.signal(sig)
            time.sleep(SECOND_SIGNAL_AFTER)
            fit.signal(sig)
            fit.wait_group(STOP)
            assert fit.popen.returncode == 0
            assert_clean_output(fit.text, "backward_fit")
    finally:
        _stop_all(procs)


def _owned_segments(pgid: int) -> set:
    """Fast DDS shared-memory segments owned by the processes of a group: those whose ``_el`` lock file
    they hold locked (``/proc/locks``); they also map the segments of the processes they read from."""
    pids = {str(p) for p in group_pids(pgid)}
    inodes = set()
    for line in Path("/proc/locks").read_text().splitlines():
        f = line.split()
        if len(f) > 5 and f[1] == "FLOCK" and f[4] in pids:
            inodes.add(int(f[5].split(":")[2]))
    return {f"/dev/shm/{name[:-3]}" for name in os.listdir("/dev/shm")
            if name.startswith("fastdds_") and name.endswith("_el") and "port" not in name
            and _inode(f"/dev/shm/{name}") in inodes}


def _inode(path: str):
    """The file's inode, None if it is gone: other DDS processes on the machine (the suite's other worker) create
    and remove their segments at any time, also between the directory listing and this look (a flake run failed
    on exactly that: FileNotFoundError for another participant's lock file)."""
    try:
        return os.stat(path).st_ino
    except FileNotFoundError:
        return None


class Watcher(Node):
    def __init__(self, context):
        super().__init__("test_watcher", context=context)
        self.status, self.theta = [], []
        self.create_subscription(String, "/backward_fit/status", lambda m: self.status.append(m.data),
                                 QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.create_subscription(Float64, "/backward_fit/theta", lambda m: self.theta.append(m.data), 10)
        self.sim = AsyncParameterClient(self, "sim_camera")


def _sim_values(ex, watcher, procs, attempts: int = 3) -> dict:
    """sim_camera's base parameters, asking again when a request goes unanswered for 15 s: right after a
    SIGKILL a request was lost now and then in full runs (1 in ~3; we suspect the killed process's
    shared-memory ports, cf. eProsima/Fast-DDS#5469); a sim_camera that stopped answering fails all three.
    A request asked again is reported as a warning (in pytest's summary), so it is counted, not hidden."""
    for i in range(attempts):
        fut = watcher.sim.get_parameters(list(RGB_NAMES))
        try:
            spin_until(ex, fut.done, 15, f"sim_camera's parameters (request {i + 1} of {attempts})",
                       detail=lambda: logs(procs))
            break
        except AssertionError:
            if i == attempts - 1:
                raise
            warnings.warn(f"sim_camera's parameters: request {i + 1} unanswered for 15 s, asked again")
    return {n: v.double_value for n, v in zip(RGB_NAMES, fut.result().values)}


@pytest.mark.slow
def test_sigkill_of_backward_fit_mid_fit_loses_nothing(trial, sim_params, tmp_path, monkeypatch):
    sim_file, sim_values = sim_params
    previous = UnderwaterParams(a=(0.5, 0.2, 0.1), b=(0.05, 0.25, 0.35), rho_f=0.1)
    out_yaml = tmp_path / "fit.yaml"
    write_params_yaml(out_yaml, previous, comment="the previous fit")
    previous_bytes = out_yaml.read_bytes()
    domain = domain_id()
    long_fit = backward_graph(sim_params=str(sim_file), bag=str(trial), output_yaml=str(out_yaml), frames=3,
                              stride=4, optimizer="cmaes", max_iter=400, keep_running=True)
    procs = _start(long_fit, domain)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    watcher = Watcher(ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(watcher)
    try:
        with logs_on_failure(procs):
            spin_until(ex, lambda: watcher.theta, START, "the fit to run (a theta message on /backward_fit/theta)")
            assert not any(s.startswith(("done", "failed")) for s in watcher.status), watcher.status
            killed = procs["backward_fit"]
            segments = _owned_segments(killed.pgid)
            assert segments, "backward_fit owns no Fast DDS segment"
            killed.signal(signal.SIGKILL)
            killed.wait_group(STOP)
            assert killed.popen.returncode == -signal.SIGKILL
            if not _beside_other_tests():                           # (else a node of another may clean first)
                assert all(Path(s).exists() for s in segments)     # what SIGKILL leaves behind

            # sim_camera kept its parameters and runs on; the file is the previous one, whole
            assert procs["sim_camera"].popen.poll() is None
            assert _sim_values(ex, watcher, procs) == sim_values
            assert out_yaml.read_bytes() == previous_bytes
            assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.yaml"]     # no temporary file left

            # restart the fitting part of the graph: it fits, re-parameterizes sim_camera, replaces the file
            procs["bag_play"].stop()
            procs["backward_fit (killed)"] = procs.pop("backward_fit")     # their logs stay in failure messages
            procs["bag_play (first)"] = procs.pop("bag_play")
            watcher.status.clear()
            quick = backward_graph(sim_params=str(sim_file), bag=str(trial), output_yaml=str(out_yaml), frames=3,
                                   stride=4, optimizer="cmaes", max_iter=3, keep_running=True)
            procs.update(_start(quick, domain, names={"backward_fit", "bag_play"}))
            spin_until(ex, lambda: any(s.startswith(("done", "failed")) for s in watcher.status), START,
                       "the restarted fit")
            assert watcher.status[-1].startswith("done") and "re-parameterized" in watcher.status[-1], watcher.status
            fitted = yaml.safe_load(out_yaml.read_text())["/**"]["ros__parameters"]
            assert _sim_values(ex, watcher, procs) == {n: fitted[n] for n in RGB_NAMES} != sim_values
            # the segments the killed one left in /dev/shm are gone: every uw_sil node removes those of dead
            # processes when it starts, so the restarted ones did, or a node of a test running beside this one
            # (two test processes) did it first; which one is not this test's to say (the rule of the clean-up:
            # test_stale_shm_segments_are_removed_only_when_their_owner_is_gone below)
            assert not any(Path(s).exists() for s in segments), segments
    finally:
        _stop_all(procs)
        ex.shutdown()
        watcher.destroy_node()
        ctx.try_shutdown()
    for name in ("sim_camera", "backward_fit", "bag_play"):          # the restarted ones and sim_camera
        assert_clean_output(procs[name].text, name)


def _beside_other_tests() -> bool:
    """Other test processes run at the same time (pytest-xdist workers of this run): their nodes remove the
    stale segments of dead processes too, whenever they start."""
    return int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1


def test_stale_shm_segments_are_removed_only_when_their_owner_is_gone(tmp_path):
    """The lock-file rule of Fast DDS segments: unlocked and not brand new -> the owner is gone."""
    def segment(name, age_s, size=1000):
        (tmp_path / name).write_bytes(b"\0" * size)
        (tmp_path / f"{name}_el").touch()
        t = time.time() - age_s
        os.utime(tmp_path / f"{name}_el", (t, t))
        return tmp_path / f"{name}_el"

    segment("fastdds_0123456789abcdef", 60)                  # dead owner
    live = segment("fastdds_fedcba9876543210", 60)           # owner alive: holds the lock
    segment("fastdds_00000000000000aa", 0.5)                 # brand new: maybe being set up
    (tmp_path / "fastdds_port7000").write_bytes(b"p")        # ports are Fast DDS' to reuse
    (tmp_path / "fastdds_port7000_el").touch()
    with open(live, "ab") as held:
        fcntl.flock(held, fcntl.LOCK_SH)
        assert clean_stale_shm_segments(tmp_path) == (1, 1000)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "fastdds_00000000000000aa", "fastdds_00000000000000aa_el", "fastdds_fedcba9876543210",
        "fastdds_fedcba9876543210_el", "fastdds_port7000", "fastdds_port7000_el"]
    assert clean_stale_shm_segments(tmp_path / "missing") == (0, 0)


class _TimerNode:
    """Stand-in for a node (no DDS): its timers are fired by the test; its log is a list."""

    def __init__(self):
        self.timers, self.log = [], []

    def create_timer(self, period, callback):
        node = self

        class T:
            cancelled = False

            def cancel(self):
                self.cancelled = True

            def fire(self):
                if not self.cancelled:
                    callback()
        t = T()
        node.timers.append(t)
        return t

    def get_logger(self):
        log = self.log

        class L:
            def warning(self, text):
                log.append(text)
        return L()

    def tick(self):
        for t in list(self.timers):
            t.fire()


@pytest.mark.parametrize("lost", [0, 1, 2, 3])
def test_a_lost_service_answer_is_asked_for_again(lost):
    """A request whose answer does not come is cancelled and sent again; the first answer of the last request
    is taken, once; an answer to a request given up on is not taken; after `attempts` lost answers, the node
    hears why."""
    from rclpy.task import Future

    from uw_sil.nodes import AskedUntilAnswered

    node, sent, answers, gave_up = _TimerNode(), [], [], []

    def send():
        sent.append(Future())
        return sent[-1]

    AskedUntilAnswered(node, send, answers.append, "reading the parameters of /sim", timeout=0.02, attempts=3,
                       on_give_up=gave_up.append)
    for i in range(lost):
        node.tick()                       # within the deadline: nothing happens
        assert len(sent) == i + 1
        time.sleep(0.05)                  # past it (sleeping longer only makes it later)
        node.tick()
    if lost < 3:
        assert len(sent) == lost + 1 and all(f.cancelled() for f in sent[:-1])
        assert len(node.log) == lost and all("asking again" in t for t in node.log)
        for f in sent[:-1]:               # a late answer to a request given up on
            f.set_result("late")
        assert answers == []
        sent[-1].set_result("answer")
        sent[-1].set_result("again")     # one answer is taken once
        assert answers == [sent[-1]] and answers[0].result() == "again" and not gave_up
        assert all(t.cancelled for t in node.timers)
    else:
        assert len(sent) == 3 and all(f.cancelled() for f in sent)
        assert answers == [] and gave_up == ["no answer to reading the parameters of /sim after 3 requests of 0 s each"]


FREEZE = """
import gc, sys
import uw_sil.nodes as un

class Node:
    def destroy_node(self):
        pass

def spin(node):
    junk = [[]]
    junk[0].append(junk)                 # a cycle made while spinning: still collected
    del junk
    print("frozen", gc.get_freeze_count(), "collected", gc.collect(), flush=True)
    return 0

sys.exit(un.run_node(Node, spin, args=[], name="freeze", exit_process={exit_process}))
"""


@pytest.mark.parametrize("exit_process", [True, False])
def test_a_node_executable_freezes_its_start_up_heap(exit_process):
    """A node executable's garbage collector no longer walks what the start-up left (full passes of 58-81 ms in
    ``sim_camera`` at 30 Hz held frames back, and the enhancer dropped one): ``run_node`` freezes it once the node
    is built; what is made later is still collected. In a process ``run_node`` does not own, nothing is frozen."""
    done = subprocess.run([sys.executable, "-c", FREEZE.format(exit_process=exit_process)], capture_output=True,
                          text=True, timeout=120, env=ros_env(domain_id()))
    assert done.returncode == 0, done.stderr[-3000:]
    m = re.search(r"frozen (\d+) collected (\d+)", done.stdout)
    assert m, done.stdout
    frozen, collected = int(m.group(1)), int(m.group(2))
    assert collected >= 1
    assert (frozen > 10000) if exit_process else frozen == 0, frozen
