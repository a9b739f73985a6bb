"""Helpers for tests that run ROS 2 nodes: a domain id per test, the environment of a node process, a
process in its own process group with its output collected, waiting on output lines, signalling the group,
the tail of each node's log for failure messages; for nodes in the test's own process, spinning an
executor until a condition holds (the ``ros`` fixture, a fresh rclpy Context on its own domain, is in
conftest.py).

Tests wait for events (a matched publisher or subscription, a service, a latched status, an output line,
a process ending), each with a generous deadline whose failure names what did not come and shows the
nodes' logs; never for a fixed time.
"""
from __future__ import annotations

import fcntl
import itertools
import os
import re
import signal
import subprocess
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Optional

_ids = itertools.count()

#: Deadline for an event that normally takes well under a second (discovery, a service answer): discovery
#: between processes took up to 3.4 s on a loaded 2-core machine; a deadline only ends a test that failed.
EVENT_TIMEOUT = 30.0

#: Domain ids (1..232; Fast DDS' port numbers end at 232) and the lock files that reserve them.
N_DOMAINS = 232
_DOMAIN_LOCKS = Path(tempfile.gettempdir()) / "uw_sil_test_ros_domains"
_held: dict = {}


def domain_id() -> int:
    """A ROS_DOMAIN_ID (1..232) that no other test on this machine uses while this test runs.

    Each id is reserved by an ``flock`` on a file in the temporary directory, held by this process until
    :func:`release_domains` (after each test, conftest.py) or its exit (a crash frees it too): two test runs
    at once (two checkouts, ``scripts/flake_check.sh`` beside a developer's run) never share a domain, so
    one run's nodes cannot answer another's. A pid-based start spreads concurrent runs over the range."""
    _DOMAIN_LOCKS.mkdir(exist_ok=True)
    st = _DOMAIN_LOCKS.stat()
    if st.st_uid == os.getuid() and st.st_mode & 0o1777 != 0o1777:
        _DOMAIN_LOCKS.chmod(0o1777)       # shared by the machine's users (sticky, as /tmp), like the domains
    start = (os.getpid() * 11 + next(_ids) * 3) % N_DOMAINS
    for k in range(N_DOMAINS):
        d = 1 + (start + k) % N_DOMAINS
        if d in _held:
            continue
        try:                              # read-only is enough for flock, also on another user's file
            f = os.fdopen(os.open(_DOMAIN_LOCKS / f"{d}.lock", os.O_RDONLY | os.O_CREAT, 0o644), "rb")
        except OSError:
            continue
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        _held[d] = f
        return d
    raise RuntimeError(f"all {N_DOMAINS} ROS domain ids are in use by running tests ({_DOMAIN_LOCKS})")


def release_domains():
    """Give back the domain ids this process reserved (their nodes must be gone)."""
    for f in _held.values():
        f.close()
    _held.clear()


def spin_until(executor, cond, timeout: float = EVENT_TIMEOUT, what: str = "condition",
               detail: Optional[Callable[[], str]] = None):
    """Spin ``executor`` until ``cond()`` is true; AssertionError naming ``what`` after ``timeout`` s, with
    ``detail()`` (e.g. what did arrive, the nodes' logs) appended."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            extra = detail() if detail is not None else ""
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}" + (f"\n{extra}" if extra else ""))
        executor.spin_once(timeout_sec=0.02)


def wait_future(executor, future, timeout: float = EVENT_TIMEOUT, what: str = "service response",
                detail: Optional[Callable[[], str]] = None):
    """Spin until an rclpy future is done and return its result."""
    spin_until(executor, future.done, timeout=timeout, what=what, detail=detail)
    return future.result()


def call_until_answered(executor, client, request, what: str, timeout: float = EVENT_TIMEOUT, every: float = 5.0,
                        detail: Optional[Callable[[], str]] = None) -> tuple:
    """Call the service of ``client`` and spin until it answers; while no answer has come ``every`` seconds after
    the last call, call again. Returns ``(response, calls)``: the first answer to any of the calls. Only for
    services that take a repeat (idempotent, or saying so in their answer).

    Why: Fast DDS drops an answer when the server has not yet matched the client's reply reader, although the
    client already sees the server (``service_is_ready``). In a loaded flake run bag_play logged "failed to send
    response (timeout): client will not receive response", had resumed and played the whole bag, and the test
    waited its 30 s for the answer (rmw_fastrtps issue 842)."""
    deadline = time.monotonic() + timeout
    futures = []
    while True:
        futures.append(client.call_async(request))
        retry_at = time.monotonic() + every
        spin_until(executor, lambda: any(f.done() for f in futures) or time.monotonic() > min(retry_at, deadline),
                   timeout=timeout + every, what=what, detail=detail)
        answered = next((f for f in futures if f.done()), None)
        if answered is not None:
            return answered.result(), len(futures)
        if time.monotonic() > deadline:
            extra = detail() if detail is not None else ""
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what} ({len(futures)} calls, none "
                                 f"answered)" + (f"\n{extra}" if extra else ""))


def ros_env(domain: int, base: Optional[dict] = None, **extra) -> dict:
    """Environment of a node process: its own domain, loopback discovery, headless OpenGL, no profile
    chosen by the caller (the nodes choose theirs)."""
    env = dict(os.environ if base is None else base)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYOPENGL_PLATFORM="osmesa",
               PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONFAULTHANDLER="1")
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    env.update(extra)
    return env


def _is_node_process(pid: int) -> bool:
    """A uw_sil node process (``python -m uw_sil.nodes.entry NODE``, or a console script in ``lib/uw_sil``)."""
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False
    return "uw_sil.nodes" in cmd or "/lib/uw_sil/" in cmd


def group_pids(pgid: int) -> list:
    """Live processes of process group ``pgid`` (zombies excluded)."""
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[2]) == pgid and fields[0] != "Z":
            pids.append(int(d.name))
    return pids


#: Lines of each node's log shown in a failure message.
TAIL_LINES = 40
#: A launcher's node prefix: ``[sim_camera  ] ...`` (uw-sil launch), ``[sim_camera-1] ...`` (ros2 launch).
_PREFIX = re.compile(r"^\[([^\]\s]+)\s*\] ")


def clean_shm():
    """Remove the Fast DDS shared-memory segments whose owner is gone (after a SIGKILL: they stay in
    /dev/shm, 35 MB each with the package's profile); the owners' lock rule leaves live runs' alone."""
    from uw_sil.nodes import clean_stale_shm_segments

    return clean_stale_shm_segments()


class Proc:
    """A command in its own process group (as a terminal job), its output lines collected."""

    def __init__(self, cmd: list, env: dict, name: str = "", cwd=None):
        self.name = name or Path(cmd[0]).name
        self.cmd = cmd
        self.popen = subprocess.Popen(cmd, env=env, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True, errors="replace",
                                      start_new_session=True)
        self.pgid = self.popen.pid
        self.lines: list = []
        self._new = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in iter(self.popen.stdout.readline, ""):
            with self._new:
                self.lines.append(line.rstrip("\n"))
                self._new.notify_all()
        with self._new:
            self._new.notify_all()

    @property
    def text(self) -> str:
        return "\n".join(self.lines)

    def tail(self, n: int = TAIL_LINES) -> str:
        """The last ``n`` output lines of each node in this process's output, headed by its state: the output
        of a launcher (``uw-sil launch``, ``ros2 launch``) is split by its ``[node]`` line prefixes, so the
        tail of one chatty node does not hide another's. Once the process has ended, read after its reader
        has taken all of its output (a message built earlier showed only the lines read so far)."""
        ended = self.popen.poll() is not None
        if ended:
            self._reader.join(timeout=5)          # everything it wrote, not what the reader had got so far
        state = f"exit status {self.popen.returncode}" if ended else "running"
        lines = list(self.lines)
        head = f"--- {self.name} (pid {self.popen.pid}, {state}): {len(lines)} lines"
        groups: dict = {}
        for line in lines:
            m = _PREFIX.match(line)
            groups.setdefault(m.group(1) if m else "", []).append(line)
        if len(groups) <= 1 or len(lines) <= n:
            shown = lines[-n:]
            return "\n".join([head + (f", the last {len(shown)}:" if len(shown) < len(lines) else ":"), *shown])
        parts = [head + ", by prefix:"]
        for key, group in groups.items():
            parts.append(f"  -- [{key or 'no prefix'}] last {min(n, len(group))} of {len(group)}:")
            parts.extend(group[-n:])
        return "\n".join(parts)

    def wait_for(self, pattern: str, timeout: float = 60.0, start: int = 0) -> re.Match:
        """The first output line (from line ``start`` on) matching regex ``pattern``; AssertionError with the
        output when it does not come within ``timeout`` s or the process ends first."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        seen = start
        with self._new:
            while True:
                for line in self.lines[seen:]:
                    m = rx.search(line)
                    if m:
                        return m
                seen = max(seen, len(self.lines))
                left = deadline - time.monotonic()
                ended = self.popen.poll() is not None and not self._reader.is_alive()
                if left <= 0 or ended:
                    why = "ended" if ended else f"did not print it within {timeout:g} s"
                    raise AssertionError(f"{self.name} {why}: waiting for {pattern!r}\n{self.tail()}")
                self._new.wait(min(left, 0.5))

    def signal(self, sig: int):
        """``sig`` to the whole process group (what a terminal's Ctrl-C does)."""
        try:
            os.killpg(self.pgid, sig)
        except ProcessLookupError:
            pass

    def wait_group(self, timeout: float) -> float:
        """Wait until every process of the group has ended; seconds it took (AssertionError after timeout,
        with the Python stacks of the node processes still running, :meth:`node_stacks`)."""
        t0 = time.monotonic()
        while group_pids(self.pgid) or self.popen.poll() is None:
            if time.monotonic() - t0 > timeout:
                left = group_pids(self.pgid)
                raise AssertionError(f"{self.name}: processes {left} still running after {timeout:g} s\n"
                                     f"{self.tail()}{self.node_stacks(left)}")
            time.sleep(0.02)
        self._reader.join(timeout=5)
        return time.monotonic() - t0

    def node_stacks(self, pids, wait: float = 2.0) -> str:
        """Ask the node processes among ``pids`` for every thread's Python stack (SIGUSR1: node processes
        register it with faulthandler, which answers from a C handler even while a call holds the GIL) and
        return what they wrote. Only processes of ours are asked: SIGUSR1 ends a process that has no handler
        for it (a launcher)."""
        nodes = [pid for pid in pids if _is_node_process(pid)]
        if not nodes:
            return ""
        seen = len(self.lines)
        for pid in nodes:
            try:
                os.kill(pid, signal.SIGUSR1)
            except ProcessLookupError:
                pass
        time.sleep(wait)           # the reader thread takes the dumps from the pipe meanwhile
        dumped = self.lines[seen:][:400]
        return (f"\n--- stacks of the node processes {nodes} still running (SIGUSR1):\n" + "\n".join(dumped)
                if dumped else f"\n--- node processes {nodes}: no stacks within {wait:g} s")

    def stop(self, timeout: float = 15.0):
        """Ctrl-C, then SIGKILL for whatever is left: nothing outlives a test."""
        if group_pids(self.pgid) or self.popen.poll() is None:
            self.signal(signal.SIGINT)
            try:
                self.wait_group(timeout)
            except AssertionError:
                self.signal(signal.SIGKILL)
                self.popen.wait(timeout=10)
                clean_shm()
        self._reader.join(timeout=5)
        if not self._reader.is_alive():
            self.popen.stdout.close()


def assert_clean_output(text: str, what: str = ""):
    """No Python traceback, KeyboardInterrupt or crash in a node's output."""
    for bad in ("Traceback", "KeyboardInterrupt", "Segmentation fault", "Fatal Python error", "exit code -"):
        assert bad not in text, f"{what}: {bad!r} in the output:\n{text}"


def logs(*procs) -> str:
    """The tails of the logs of ``procs`` (Proc objects, or dicts / lists of them): for failure messages."""
    flat = []
    for p in procs:
        if isinstance(p, dict):
            flat.extend(p.values())
        elif isinstance(p, (list, tuple)):
            flat.extend(p)
        elif p is not None:
            flat.append(p)
    return "\n".join(p.tail() for p in flat)


@contextmanager
def logs_on_failure(*procs):
    """A failed assertion inside the block gets the tail of each process's log appended to its message
    (``procs`` as for :func:`logs`, read when it fails: a dict the block fills is shown as it is then)."""
    try:
        yield
    except AssertionError as e:
        text = logs(*procs)
        if text:
            e.args = (f"{e.args[0] if e.args else ''}\n{text}", *e.args[1:])
        raise

