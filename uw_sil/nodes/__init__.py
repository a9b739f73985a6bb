"""The ROS 2 room: thin rclpy adapters around the core library (parameters, topics, services, message
conversion), the node graphs (:mod:`.graph`) that feed both the launch files (:mod:`.launchgen`) and
``uw-sil launch`` (:mod:`.launcher`).

Import rules: the only room that imports rclpy and ROS message packages (inside the node modules and
:mod:`.launchgen`; this ``__init__``, :mod:`.graph` and :mod:`.launcher` import no ROS at module level).
No algorithm lives here: nodes call :mod:`uw_sil.sim`, :mod:`uw_sil.fit`, :mod:`uw_sil.bags`.
"""
from __future__ import annotations

import faulthandler
import importlib
import os
import re
import signal
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Optional

#: Environment variable naming the Fast DDS XML profile; nodes set it to the package's profile when unset.
FASTDDS_PROFILE_VAR = "FASTDDS_DEFAULT_PROFILES_FILE"


def help_requested(args=None) -> bool:
    """``-h``/``--help`` among the node's own arguments (those before ``--ros-args``)."""
    argv = list(sys.argv[1:] if args is None else args)
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    return "-h" in own or "--help" in own


def use_fastdds_profile(environ=None) -> str:
    """Point ``FASTDDS_DEFAULT_PROFILES_FILE`` at ``config/fastdds_shm.xml`` unless it is already set.

    Fast DDS' default transports lose large images between processes (640x480 rgb8 at 30 Hz: 59 of 150
    delivered); the profile (a 32 MiB shared-memory segment plus UDP on loopback) delivered all. Fast DDS
    reads the variable when the first participant is created, so this must run before ``rclpy.init``.
    Returns the profile in effect (the caller's own when it had set one).
    """
    env = os.environ if environ is None else environ
    if not env.get(FASTDDS_PROFILE_VAR):
        from .graph import share_file

        env[FASTDDS_PROFILE_VAR] = str(share_file("config", "fastdds_shm.xml"))
    return env[FASTDDS_PROFILE_VAR]


_SEGMENT_LOCK = re.compile(r"^fastdds_[0-9a-f]{16}_el$")


def clean_stale_shm_segments(shm_dir="/dev/shm", min_age_s: float = 2.0) -> tuple:
    """Remove Fast DDS shared-memory segments whose owner process is gone; returns (segments, bytes).

    Each Fast DDS segment ``fastdds_<16 hex>`` has a lock file ``<segment>_el`` that its owner holds
    locked (``flock``) while it lives. A process killed with SIGKILL leaves both behind (35 MB each with
    this package's profile; they pile up in /dev/shm, which is RAM). A lock file nobody holds marks a
    dead owner; files younger than ``min_age_s`` are left alone (their owner may still be setting them
    up). This is the rule of Fast DDS' own ``fastdds shm clean`` for segments; port files (52 kB each)
    are reused by Fast DDS and left alone.
    """
    import fcntl

    shm = Path(shm_dir)
    try:
        names = os.listdir(shm)
    except OSError:
        return 0, 0
    removed, freed, now = 0, 0, time.time()
    for name in names:
        if not _SEGMENT_LOCK.match(name):
            continue
        lock, segment = shm / name, shm / name[:-3]
        try:
            if now - lock.stat().st_mtime < min_age_s:
                continue
            with open(lock, "ab") as f:
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    continue                     # held: the owner is alive
                size = segment.stat().st_size if segment.exists() else 0
                segment.unlink(missing_ok=True)
                lock.unlink(missing_ok=True)
        except OSError:                          # gone meanwhile, or another user's file
            continue
        removed, freed = removed + 1, freed + size
    return removed, freed


def declare_string_array(node, name: str, descriptor) -> list:
    """Declare a string-array parameter that has a value even when nobody gives one (then ``[]``).

    rclpy types an empty default list as a byte array, and a parameter declared by type alone stays
    unset: ``ros2 param get`` says "Parameter not set" and ``ros2 param dump`` of the node comes back
    empty. So: declare by type, give it an empty string array if nothing overrode it, then apply the
    descriptor (which may make it read-only). Returns the value.
    """
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import ParameterUninitializedException
    from rclpy.parameter import Parameter

    node.declare_parameter(name, Parameter.Type.STRING_ARRAY,
                           ParameterDescriptor(description=descriptor.description))
    try:
        node.get_parameter(name)
    except ParameterUninitializedException:
        node.set_parameters([Parameter(name, Parameter.Type.STRING_ARRAY, [])])
    descriptor.type = Parameter.Type.STRING_ARRAY.value
    node.set_descriptor(name, descriptor)
    return list(node.get_parameter(name).value)


#: Seconds a service's answer may take before the request is sent again (:class:`AskedUntilAnswered`)
ANSWER_TIMEOUT = 5.0


class AskedUntilAnswered:
    """A service request sent again when its answer does not come within ``timeout`` seconds.

    A lost answer must not become a node that waits for ever. Fast DDS does lose them: a server that has not
    yet matched the client's response reader gives up on its answer ("failed to send response (timeout):
    client will not receive response", rmw_fastrtps), and the client's future then never completes (seen in
    the suite: an enhancer waiting for ``sim_camera``'s parameters until its bag player gave up). Every request
    made through this class must be idempotent (reading or setting the same values again).

    ``send()`` makes the request and returns its future; ``on_answer(future)`` is called with the first answer
    (from the executor's thread); after ``attempts`` unanswered requests ``on_give_up(text)``. A node timer
    watches the deadline, so the node must be spinning.
    """

    def __init__(self, node, send: Callable, on_answer: Callable, what: str, timeout: float = ANSWER_TIMEOUT,
                 attempts: int = 6, on_give_up: Optional[Callable] = None):
        import threading

        self.node, self._send, self._on_answer, self.what = node, send, on_answer, what
        self.timeout, self.attempts, self._on_give_up = float(timeout), int(attempts), on_give_up
        self._lock = threading.Lock()
        self.attempt = 0
        self._future = None
        self._asked_at = 0.0
        self._ended = False
        self._timer = node.create_timer(min(0.25, self.timeout / 4), self._check)
        self._ask()

    def _ask(self):
        with self._lock:
            self.attempt += 1
            self._asked_at = time.monotonic()
            self._future = fut = self._send()
        fut.add_done_callback(self._answered)

    def _answered(self, fut):
        with self._lock:
            if fut is not self._future or fut.cancelled() or self._ended:
                return          # an answer given up on (a later request is out), or cancelled here
            self._ended = True
        self._timer.cancel()
        self._on_answer(fut)

    def _check(self):
        with self._lock:
            if self._ended:
                self._timer.cancel()
                return
            late = time.monotonic() - self._asked_at > self.timeout
            fut = self._future
            give_up = late and self.attempt >= self.attempts
            if give_up:
                self._ended = True
        if not late:
            return
        fut.cancel()            # the client forgets the request (rclpy removes it from its pending ones)
        if give_up:
            self._timer.cancel()
            text = f"no answer to {self.what} after {self.attempts} requests of {self.timeout:.0f} s each"
            if self._on_give_up is not None:
                self._on_give_up(text)
            return
        self.node.get_logger().warning(f"no answer to {self.what} within {self.timeout:.0f} s; asking again "
                                       f"(request {self.attempt + 1} of at most {self.attempts})")
        self._ask()


@contextmanager
def executor_for(node):
    """A SingleThreadedExecutor serving ``node``, shut down on leaving (also on Ctrl-C).

    An executor left to the garbage collector after Ctrl-C interrupted its wait (a suspended generator
    holding rcl handles, in a reference cycle) crashed the process when collected later (segmentation
    fault in ``gc.collect`` inside pyrender's context deletion, 1 in 10 shutdowns of backward_fit);
    shutting it down here releases those handles while everything is still alive.
    """
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    try:
        yield executor
    finally:
        import rclpy

        _settle_signals(rclpy)      # the executor's SIGINT guard condition is destroyed next
        executor.shutdown(timeout_sec=1.0)


def _ignore_signals():
    """From here on SIGINT/SIGTERM are ignored: the node is cleaning up and about to exit.

    A terminal's Ctrl-C reaches the node and ``ros2 launch`` forwards another; a second signal must not
    interrupt destroying the node or closing the renderer (KeyboardInterrupt traces, exit code -2), nor
    kill the interpreter while it finalizes (Python then restores the default action, except for
    ignored signals). ``rclpy.try_shutdown`` re-installs the handlers it found at init, so this is
    called again after it."""
    for s in (signal.SIGINT, signal.SIGTERM):
        try:
            signal.signal(s, signal.SIG_IGN)
        except ValueError:   # not the main thread (a node run inside a test): leave signals alone
            return


def run_node(make_node: Callable, spin: Optional[Callable] = None, args=None, name: str = "",
             user_errors: tuple = (), doc: str = "", exit_process: bool = True) -> int:
    """The ``main()`` every node shares: init, build, spin, clean shutdown; returns the exit code.

    With ``-h``/``--help`` it prints ``doc`` (the node module's docstring: topics, parameters) and
    returns 0 without starting ROS.

    Before ``rclpy.init``: the Fast DDS profile (:func:`use_fastdds_profile`), however the node is started
    (``ros2 run``, ``ros2 launch``, ``uw-sil launch``, the console script), unless the caller set one; and
    shared-memory segments left by killed processes are removed (:func:`clean_stale_shm_segments`).

    ``spin(node)`` returns an exit code (default: ``rclpy.spin``, code 0). Ctrl-C / SIGTERM are a clean
    stop with exit code 0, also during start-up and also when repeated: once spinning has ended, further
    SIGINT/SIGTERM are ignored (:func:`_ignore_signals`), and stay ignored when ``run_node`` returns (the
    process is about to exit).
    Exceptions in ``user_errors`` (bad parameters such as a missing bag) are logged, exit code 1.

    With ``exit_process`` (what the node executables do) the process ends right after the clean-up
    (``os._exit`` once stdout/stderr are flushed): everything the node holds is released by then (node
    destroyed, rclpy shut down, which removes its Fast DDS shared-memory segments; renderer closed; files
    are written atomically), and the interpreter's own finalization took another 1.3-1.5 s per node
    here, which made a graph need more than 5 s to stop. Otherwise the exit code is returned.
    Once the node is built, the executables freeze what the start-up left out of the garbage collector's full
    passes (:func:`_freeze_start_up_heap`).
    The executables' teardown is bounded (:func:`teardown_deadline`): one stuck in the middleware ends
    the process after :data:`TEARDOWN_DEADLINE` with its stacks on stderr and exit code 1.
    """
    if help_requested(args):
        print(f"usage: ros2 run uw_sil {name or 'NODE'} [--ros-args -p NAME:=VALUE | --params-file FILE | "
              f"-r FROM:=TO ...]\n\n{doc.strip()}")
        return 0
    _handle_stop_signals()
    if exit_process:
        _report_crashes()
        _pass_over_stop_debris()
    try:
        code = _run_node(make_node, spin, args, name, user_errors, exit_process)
    except KeyboardInterrupt:                       # a signal in the few instructions around the clean-up
        code = 0
    finally:
        _ignore_signals()
    if exit_process:
        _flush_output()
        os._exit(code)
    return code


#: The node modules under :mod:`uw_sil.nodes` (each a console script of the same name, :mod:`.entry`).
NODES = ("sim_camera", "backward_fit", "bag_play", "enhancer", "panel_pose")


def start_node(module: str) -> int:
    """Import ``uw_sil.nodes.<module>`` and return its ``main()``; 0 when a stop signal came first.

    The stop signals are handled before the import (rclpy, scipy, the renderer: 1-3 s): Ctrl-C or SIGTERM
    then is a clean stop without a traceback, like one during :func:`run_node` (see :mod:`.entry`)."""
    if module not in NODES:
        raise ValueError(f"unknown node {module!r} (one of {', '.join(NODES)})")
    _handle_stop_signals()
    _report_crashes()
    _pass_over_stop_debris()
    try:
        node_module = importlib.import_module(f"{__name__}.{module}")
    except BaseException:
        if not _stop_signals:          # a real import error: show it
            raise
        _ignore_signals()
        return 0
    if _stop_signals:
        # the signal came, but its KeyboardInterrupt did not: raised inside a finalizer or a weakref callback
        # of the import machinery (``_get_module_lock.<locals>.cb``), it is reported, not raised, and the import
        # went on. The node then started and ran until killed (a loaded test run: "still running after 5 s").
        _ignore_signals()
        return 0
    return node_module.main()


def _flush_output():
    """Flush stdout and stderr, whatever state they are in (closed, a broken pipe)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass


def _report_crashes():
    """A node process that crashes (SIGSEGV, SIGABRT, SIGBUS, SIGFPE, SIGILL in the middleware or the
    renderer) writes every thread's Python stack to stderr first (:func:`faulthandler.enable`), which the
    launcher shows; it still dies of the signal. Without it the launch log said only "killed by SIGSEGV"
    (``bag_play`` at Ctrl-C, once in 160 stops of the backward graph here)."""
    faulthandler.enable(file=sys.__stderr__, all_threads=True)
    # and on request: SIGUSR1 writes the stacks of a node that seems stuck (the tests ask a node that did not
    # stop in time; by hand: kill -USR1 PID); answered from a C handler, also while a call holds the GIL
    faulthandler.register(signal.SIGUSR1, file=sys.__stderr__, all_threads=True, chain=False)


def _pass_over_stop_debris():
    """After a stop signal, two errors the interpreter reports but cannot raise (``sys.unraisablehook``) are
    not printed; every other one still is.

    Our SIGINT/SIGTERM handler raises KeyboardInterrupt wherever the main thread is. Landing inside rclpy's
    ``Task`` constructor, before ``Future.__init__`` has set ``_exception``, it leaves a half-built task,
    whose ``__del__`` then fails with ``AttributeError: 'Task' object has no attribute '_exception'``
    ("Exception ignored in: Future.__del__" and a traceback in the node's log; ``backward_fit``, once in a
    fresh-clone test run). That object is the interrupted callback's and nothing depends on it.

    ``OSError: Signal 2 ignored due to race condition``: CPython's report of a signal that arrived while its
    handler was being set to SIG_IGN (:func:`_ignore_signals`, or rclpy's ``uninstall_signal_handlers``, which
    puts the interpreter's handler back for an instant before it restores SIG_IGN): the signal is ignored, as
    asked. ``ros2 launch`` forwards a second SIGINT after the terminal's; once in eight loaded test runs it
    landed there and the traceback failed a graph test although the node ended cleanly (reproduced: 18 in 300
    stops with SIGINTs arriving throughout the clean-up).

    And a ``KeyboardInterrupt`` raised by our handler inside a finalizer: the second SIGINT landing while the
    first one's unwinding closes a generator (``bag_play``'s bag reader, whose ``finally`` tallies what was
    read; a CI run's graph test failed on its "Exception ignored in: <generator object _raw_stream>"). The
    node is already stopping; CPython cannot raise it there anyway. Also the first signal's, landing in a
    weakref callback of the import machinery while a node still imports: the node stops all the same
    (:func:`start_node` checks the signals noted)."""
    default = sys.unraisablehook
    if getattr(default, "uw_sil_stop_debris", False):      # installed already (start_node, then run_node)
        return
    ignored = {f"Signal {int(s)} ignored due to race condition" for s in (signal.SIGINT, signal.SIGTERM)}

    def hook(unraisable):
        where, exc = unraisable.object, unraisable.exc_value
        if (_stop_signals and isinstance(exc, AttributeError)
                and getattr(where, "__module__", "") == "rclpy.task"
                and getattr(where, "__qualname__", "") == "Future.__del__"):
            return
        if _stop_signals and isinstance(exc, OSError) and str(exc) in ignored:
            return
        if _stop_signals and isinstance(exc, KeyboardInterrupt):
            return
        default(unraisable)

    hook.uw_sil_stop_debris = True
    sys.unraisablehook = hook


def _handle_stop_signals():
    """SIGTERM stops a node like Ctrl-C, also while it starts; both are noted (see :func:`_interrupt`)."""
    try:
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, _interrupt)
    except ValueError:                              # not the main thread: leave signals alone
        pass


#: Stop signals this process received (see :func:`_interrupt`).
_stop_signals: list = []


def _interrupt(signum, _frame):
    """SIGINT/SIGTERM: note it, raise KeyboardInterrupt. Noted, because the KeyboardInterrupt does not always
    arrive as one: raised while ctypes converts an argument (an OpenGL call of the renderer) it comes out
    as ``ctypes.ArgumentError('argument 2: KeyboardInterrupt')``."""
    _stop_signals.append(signum)
    raise KeyboardInterrupt


#: How long a stopped node waits for rclpy's signal thread to shut the context down (it takes ~0.1 ms).
SIGNAL_SHUTDOWN_WAIT = 2.0


def _await_signal_shutdown(rclpy, timeout: float = SIGNAL_SHUTDOWN_WAIT):
    """Wait until rclpy's own SIGINT/SIGTERM handler has shut the context down.

    That handler does not shut down in the signal's thread: it wakes a thread of rclpy's that shuts
    down every context while our handler raises KeyboardInterrupt in the main thread. Destroying the
    node's publishers while that thread is inside ``rcl_shutdown`` crashed a node (SIGSEGV in
    ``destroy_publisher``, once in a CI run). ``rcl_shutdown`` marks the context invalid as its last
    step, so once ``rclpy.ok()`` is False the node can be destroyed the usual way."""
    deadline = time.monotonic() + timeout
    while rclpy.ok() and time.monotonic() < deadline:
        time.sleep(0.002)


#: Longest a node executable's teardown (``destroy_node``, ``rclpy.try_shutdown``) may take. rclpy's part
#: takes well under 1 s; the longest wait of our own in a ``destroy_node`` is the enhancer's for its
#: worker's last frame (5 s), the backward fit's for its fit thread is 3 s.
TEARDOWN_DEADLINE = 8.0


@contextmanager
def teardown_deadline(seconds: float = TEARDOWN_DEADLINE, armed: bool = True):
    """Bound the teardown of a node process: past ``seconds`` faulthandler writes ``Timeout (0:00:08)!`` and
    every thread's stack to stderr (the main thread's shows where the teardown stuck), and the process
    exits with code 1.

    Why: once (a fresh-clone test run, quiet machine) ``sim_camera`` never ended after Ctrl-C. Its main
    thread was inside rclpy's ``Node.destroy_node`` (``destroy_when_not_in_use``: the middleware deleting
    the node), still 7 minutes later. That call holds the GIL, so no Python thread could end
    it; :func:`faulthandler.dump_traceback_later` runs its timer in a C thread that needs no GIL.
    Exit code 1, not 0: the teardown did not finish (Fast DDS may have left shared-memory segments, which
    the next node start removes, :func:`clean_stale_shm_segments`).

    The likely cause, caught since with gdb in processes that imitate the nodes' teardown (19 hangs, one native
    stack every time; in the real ``sim_camera`` not caught): a deadlock inside Fast DDS 3.2. Its receive
    thread, holding the participant's discovery (PDP) mutex, processes a peer's removal of a writer one of
    this process's reliable readers is matched to and waits for the event thread (``WriterProxy::stop`` ->
    ``ResourceEvent::unregister_timer``); the event thread, in the participant's announcement
    (``PDP::set_next_announcement_interval``), waits for that mutex. Every later teardown step that stops a
    timer (deleting a writer, the participant) then waits for ever, at no CPU (the 94 % reported once was
    probably ps's average over the process's life). It forms when peers leave while the announcement fires:
    once in about 1500 imitated teardowns at the default announcement period, 11 in 3013 with it at 20 ms
    (upstream class: eProsima/Fast-DDS#6502). Nothing here can undo it, so the deadline ends the process.
    Not armed when ``armed`` is False: a node run inside another program (a test) must not end it.
    """
    if not armed:
        yield
        return
    _flush_output()                           # what was logged before comes first
    faulthandler.dump_traceback_later(seconds, exit=True, file=sys.__stderr__)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


def _settle_signals(rclpy):
    """After a stop signal, before destroying anything rclpy's signal thread touches: let that thread finish
    its work for the signal (wake every executor's SIGINT guard condition, then shut the contexts down), then
    end it. From here on stop signals are ignored.

    That thread walks the list of SIGINT guard conditions while an executor being shut down frees the list
    and destroys its guard condition (rclpy's ``signal_handler.cpp``). Measured with a process that
    publishes 640x480 images and is stopped by SIGINT: 3 SIGSEGV in 1450 stops with the executor shut down
    right after the KeyboardInterrupt, two with a stack (in ``SignalHandlerGuardCondition.__del__`` during
    the executor's shutdown, and in the next call), none in 1000 stops with this done first. ``bag_play``
    died of SIGSEGV at Ctrl-C once in 160 stops of the backward graph here; no stack was recorded then
    (:func:`_report_crashes` records it now), so that this was its cause is likely, not shown.
    Ignoring the signals first means no later signal wakes the thread again; ``uninstall_signal_handlers``
    joins it. No-op when no stop signal came (a node that ended by itself; a node run inside a test,
    whose process keeps its handlers)."""
    if not _stop_signals:
        return
    _ignore_signals()
    _await_signal_shutdown(rclpy)
    from rclpy.signals import uninstall_signal_handlers

    uninstall_signal_handlers()     # joins the thread; puts back the handler it finds (SIG_IGN, set above)
    _ignore_signals()


def _freeze_start_up_heap():
    """Collect once, then move every object the start-up left (rclpy, scipy, the renderer, the node) to the
    interpreter's permanent generation (``gc.freeze``), so the garbage collector's full passes no longer walk it.

    A full pass walks every tracked object. In a node at 30 Hz that took 58 and 81 ms in ``sim_camera`` (two passes
    in 30 s of the forward graph, 640x480): the frames held back by the first were then published together and the
    enhancer, whose queue holds 2, dropped one (a frame 326 of 900 in 5 of 6 runs, before and after the one-pass
    render). Frozen, a full pass took 0.3 ms and the run lost none. What the node creates later is collected as
    before; the frozen objects are its lifetime's anyway (only node executables do this: they own their
    process)."""
    import gc

    gc.collect()
    gc.freeze()


def _run_node(make_node, spin, args, name, user_errors, exit_process: bool = True) -> int:
    profile = use_fastdds_profile()
    stale = clean_stale_shm_segments()
    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.logging import get_logger

    logger = get_logger(name or "uw_sil")
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        if _stop_signals:
            # a stop signal before rclpy's handlers were in whose KeyboardInterrupt a finalizer swallowed
            # (:func:`start_node`): stop now, as rclpy would have on it
            raise KeyboardInterrupt
        logger.debug(f"{FASTDDS_PROFILE_VAR}={profile}")
        if stale[0]:
            logger.info(f"removed {stale[0]} Fast DDS shared-memory segment(s) ({stale[1] / 2**20:.0f} MiB) "
                        "left in /dev/shm by killed processes")
        node = make_node()
        if exit_process:
            _freeze_start_up_heap()
        if spin is None:
            rclpy.spin(node)
        else:
            code = spin(node) or 0
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (*user_errors, ParameterException) as e:
        _ignore_signals()
        if not _stop_signals:
            logger.error(str(e))
            code = 1
    except Exception:
        _ignore_signals()
        if rclpy.ok() and not _stop_signals:   # an error, not a stop request that surfaced as one
            raise
    finally:
        _ignore_signals()
        try:
            with teardown_deadline(armed=exit_process):
                _settle_signals(rclpy)
                if node is not None:
                    node.destroy_node()
                rclpy.try_shutdown()
        except KeyboardInterrupt:   # between rclpy's handlers and ours: the clean-up is done enough
            pass
        _ignore_signals()           # rclpy.try_shutdown restored the handlers it found at init
    return code


def camera_from_file(path: str, frame_id: str = "camera_optical_frame"):
    """The camera of a ROS ``camera_calibration`` YAML file (``camera_info_url``-style ``camera_info_file``
    parameter of the nodes, for recordings without ``camera/camera_info``); ValueError when it has lens
    distortion: the nodes take rectified images (rectify upstream, e.g. image_proc; the offline commands
    rectify themselves, ``--camera-info``)."""
    from ..bags.camera_yaml import load_camera_yaml

    calib = load_camera_yaml(path)
    if calib.has_distortion:
        raise ValueError(f"camera_info_file {path} has lens distortion ({calib.distortion_model} "
                         f"{list(map(float, calib.D))}): the nodes take rectified images only")
    return calib.raw_camera(frame_id)
