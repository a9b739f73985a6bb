"""Helpers for tests that run ROS 2 nodes: a domain id per test, the environment of a node process, a
process in its own process group with its output collected, waiting on output lines, signalling the group;
for nodes in the test's own process, spinning an executor until a condition holds (the ``ros`` fixture,
a fresh rclpy Context on its own domain, is in conftest.py)."""
from __future__ import annotations

import itertools
import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Optional

_ids = itertools.count()


def domain_id() -> int:
    """A ROS_DOMAIN_ID (1..232) unlikely to be used by a concurrent test run or another test here
    (offset from test_nodes' ids)."""
    return 1 + (os.getpid() * 11 + 117 + next(_ids) * 3) % 232


def spin_until(executor, cond, timeout: float = 20.0, what: str = "condition"):
    """Spin ``executor`` until ``cond()`` is true; AssertionError naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        executor.spin_once(timeout_sec=0.02)


def wait_future(executor, future, timeout: float = 20.0, what: str = "service response"):
    """Spin until an rclpy future is done and return its result."""
    spin_until(executor, future.done, timeout=timeout, what=what)
    return future.result()


def ros_env(domain: int, base: Optional[dict] = None, **extra) -> dict:
    """Environment of a node process: its own domain, loopback discovery, headless OpenGL, no profile
    chosen by the caller (the nodes choose theirs)."""
    env = dict(os.environ if base is None else base)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYOPENGL_PLATFORM="osmesa",
               PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONFAULTHANDLER="1")
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    env.update(extra)
    return env


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
                    raise AssertionError(f"{self.name} {why}: waiting for {pattern!r}\n--- output:\n{self.text}")
                self._new.wait(min(left, 0.5))

    def signal(self, sig: int):
        """``sig`` to the whole process group (what a terminal's Ctrl-C does)."""
        try:
            os.killpg(self.pgid, sig)
        except ProcessLookupError:
            pass

    def wait_group(self, timeout: float) -> float:
        """Wait until every process of the group has ended; seconds it took (AssertionError after timeout)."""
        t0 = time.monotonic()
        while group_pids(self.pgid) or self.popen.poll() is None:
            if time.monotonic() - t0 > timeout:
                raise AssertionError(f"{self.name}: processes {group_pids(self.pgid)} still running after "
                                     f"{timeout:g} s\n--- output:\n{self.text}")
            time.sleep(0.02)
        self._reader.join(timeout=5)
        return time.monotonic() - t0

    def stop(self, timeout: float = 15.0):
        """Ctrl-C, then SIGKILL for whatever is left: nothing outlives a test."""
        if group_pids(self.pgid) or self.popen.poll() is None:
            self.signal(signal.SIGINT)
            try:
                self.wait_group(timeout)
            except AssertionError:
                self.signal(signal.SIGKILL)
                self.popen.wait(timeout=10)
        self._reader.join(timeout=5)


def assert_clean_output(text: str, what: str = ""):
    """No Python traceback, KeyboardInterrupt or crash in a node's output."""
    for bad in ("Traceback", "KeyboardInterrupt", "Segmentation fault", "Fatal Python error", "exit code -"):
        assert bad not in text, f"{what}: {bad!r} in the output:\n{text}"
