"""Start a node graph of :mod:`uw_sil.nodes.graph` as processes: ``ros2 launch`` for pip installs.

``launch``/``launch_ros`` are not on PyPI, so ``uw-sil launch GRAPH`` does their job for this package's
graphs: one process per node (``python -m uw_sil.nodes.<name> --ros-args ...``), each output line
prefixed with ``[node]``, and the environment every node needs. Nothing here imports ROS.

Behaviour
---------
* ``FASTDDS_DEFAULT_PROFILES_FILE`` points at the package's ``config/fastdds_shm.xml`` (shared memory
  plus loopback UDP: Fast DDS's defaults lose large images between processes), unless the caller's
  environment already names a profile, which is then kept.
* Ctrl-C / SIGTERM is forwarded once as SIGINT to every node (each runs in its own process group,
  so a terminal's Ctrl-C does not reach the nodes twice); nodes get ``stop_timeout`` seconds to
  exit, then SIGTERM, and SIGKILL only as the last resort (that leaves Fast DDS shared-memory
  segments in /dev/shm, and is reported). A second Ctrl-C sends SIGTERM at once, a third SIGKILL.
* A node marked ``required`` (:attr:`uw_sil.nodes.graph.NodeSpec.required`) ends the graph when it exits,
  like ``on_exit=Shutdown()`` in a launch file: in the backward graph with a bag, ``backward_fit``
  exits once the fit is done, so ``uw-sil launch backward --bag trial.mcap`` returns by itself.
  Without a bag (live camera) or with ``--keep-running`` everything runs until Ctrl-C, as with
  ``ros2 launch``.
* A node that exits with an error (non-zero status, or a signal the launcher did not send) stops
  the whole graph and the launcher exits with status 1, naming the node and its reason (the last
  ``[ERROR]``/``[FATAL]`` line or exception it printed). A node ending normally (``bag_play`` at the
  end of the bag) ends only itself.
* The options of ``uw-sil launch GRAPH`` are the graph's arguments (:class:`uw_sil.nodes.graph.GraphArg`),
  the same as the launch file's, checked the same way.
* Exit status: 0 when the graph ended normally or was stopped cleanly by Ctrl-C/SIGTERM, 1 when a
  node failed or had to be killed.
* Children get ``PR_SET_PDEATHSIG`` (Linux): if the launcher itself is killed, they receive SIGTERM
  and shut down instead of running on orphaned.
"""
from __future__ import annotations

import ctypes
import os
import selectors
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, TextIO

from . import graph as _graph

__all__ = ["launch", "graph_environment", "add_commands", "NodeProcess"]

#: Seconds a node gets to exit after SIGINT before it is sent SIGTERM (and as long again before SIGKILL).
STOP_TIMEOUT = 10.0


@dataclass
class NodeProcess:
    spec: _graph.NodeSpec
    popen: subprocess.Popen
    buffer: bytes = b""
    returncode: Optional[int] = None
    signalled: bool = False   # the launcher sent it a signal: a signal exit is then not a failure
    reason: str = ""          # the last problem the node reported in its output

    @property
    def failed(self) -> bool:
        rc = self.returncode
        if rc is None or rc == 0:
            return False
        return not (self.signalled and rc in (-signal.SIGINT, -signal.SIGTERM))


def graph_environment(base: Optional[dict] = None) -> dict:
    """Environment of the node processes: ``base`` (default ``os.environ``) plus the Fast DDS profile."""
    env = dict(os.environ if base is None else base)
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(_graph.share_file("config", "fastdds_shm.xml")))
    env["PYTHONUNBUFFERED"] = "1"              # node output reaches the terminal line by line
    env.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "0")
    return env


def _die_with_parent():
    """In the child before exec: own process group, SIGTERM when the launcher dies (Linux)."""
    os.setpgid(0, 0)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)          # PR_SET_PDEATHSIG
    except (OSError, AttributeError):          # not Linux: the process group still isolates Ctrl-C
        pass


def _emit(out: TextIO, name: str, data: bytes, width: int):
    for line in data.decode(errors="replace").splitlines():
        out.write(f"[{name:<{width}}] {line}\n")
    out.flush()


def launch(specs: list, env: Optional[dict] = None, out: TextIO = sys.stdout,
           stop_timeout: float = STOP_TIMEOUT, python: str = sys.executable) -> int:
    """Run the nodes of ``specs`` until the graph ends; return the exit status (see module docstring)."""
    if not specs:
        raise ValueError("empty graph: nothing to launch")
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"node names must be unique, got {names}")
    env = graph_environment(env)
    width = max(len(n) for n in names)
    out.write(f"[launch] FASTDDS_DEFAULT_PROFILES_FILE={env['FASTDDS_DEFAULT_PROFILES_FILE']}\n")

    stop_requested: list = []

    def on_signal(signum, _frame):
        stop_requested.append(signum)

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    procs: list = []
    sel = selectors.DefaultSelector()
    try:
        for spec in specs:
            cmd = _graph.command_line(spec, python=python)
            p = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, preexec_fn=_die_with_parent)
            np_ = NodeProcess(spec, p)
            procs.append(np_)
            sel.register(p.stdout, selectors.EVENT_READ, np_)
            out.write(f"[launch] started {spec.name} (pid {p.pid}): {' '.join(cmd[1:])}\n")
        out.flush()
        status = _supervise(procs, sel, stop_requested, out, width, stop_timeout)
    finally:
        # Whatever happened (even an exception here), no node outlives the launcher.
        for np_ in procs:
            if np_.popen.poll() is None:
                np_.popen.kill()
                np_.popen.wait()
        sel.close()
        for s, h in previous.items():
            signal.signal(s, h)
    return status


def _supervise(procs, sel, stop_requested, out, width, stop_timeout) -> int:
    stopping_since = None
    reason = None
    escalated = 0
    signals_at_stop = 0
    while True:
        for key, _ in sel.select(timeout=0.1):
            np_ = key.data
            chunk = os.read(key.fileobj.fileno(), 65536)
            if not chunk:
                sel.unregister(key.fileobj)
                continue
            data = np_.buffer + chunk
            lines, _, np_.buffer = data.rpartition(b"\n")
            if lines:
                _emit(out, np_.spec.name, lines, width)
                _note_reason(np_, lines)
        for np_ in procs:
            if np_.returncode is None and np_.popen.poll() is not None:
                np_.returncode = np_.popen.returncode
                _drain(sel, np_, out, width)
                how = f"exited with status {np_.returncode}" if np_.returncode >= 0 else \
                    f"was killed by {signal.Signals(-np_.returncode).name}"
                out.write(f"[launch] {np_.spec.name} {how}{' (FAILED)' if np_.failed else ''}\n")
                if stopping_since is None:
                    if np_.failed:
                        reason = f"{np_.spec.name} failed" + (f" ({np_.reason})" if np_.reason else "")
                    elif np_.spec.required:
                        reason = f"required node {np_.spec.name} ended"
        if stopping_since is None and stop_requested:
            reason = f"{signal.Signals(stop_requested[0]).name} received"
        running = [p for p in procs if p.returncode is None]
        if not running:
            break
        now = time.monotonic()
        if stopping_since is None and reason is not None:
            signals_at_stop = len(stop_requested)   # before writing: a Ctrl-C during the write is a second one
            out.write(f"[launch] {reason}: stopping {', '.join(p.spec.name for p in running)}\n")
            _signal_all(running, signal.SIGINT)
            stopping_since = now
        elif stopping_since is not None and escalated < 2 and (
                now - stopping_since > stop_timeout * (escalated + 1)
                or len(stop_requested) > signals_at_stop + escalated):  # at once on another Ctrl-C
            sig = signal.SIGTERM if escalated == 0 else signal.SIGKILL
            out.write(f"[launch] {', '.join(p.spec.name for p in running)} still running after "
                      f"{now - stopping_since:.1f} s: sending {sig.name}"
                      + (" (leaves Fast DDS segments in /dev/shm)" if sig == signal.SIGKILL else "") + "\n")
            _signal_all(running, sig)
            escalated += 1
        out.flush()
    failed = [p.spec.name + (f" ({p.reason})" if p.reason else "") for p in procs if p.failed]
    out.write(f"[launch] done: {'FAILED: ' + ', '.join(failed) if failed else 'all nodes ended cleanly'}\n")
    out.flush()
    return 1 if failed else 0


def _note_reason(np_, data: bytes):
    """Keep the last problem the node reported: a chunk of output without one leaves the earlier reason (a line
    printed after the error line, read separately, made the launcher forget why the node failed)."""
    np_.reason = _graph.failure_reason(data.decode(errors="replace").splitlines()) or np_.reason


def _drain(sel, np_, out, width):
    """Print what a node wrote before exiting."""
    f = np_.popen.stdout
    try:
        sel.unregister(f)
    except KeyError:
        pass
    rest = np_.buffer + f.read()
    np_.buffer = b""
    if rest:
        _emit(out, np_.spec.name, rest, width)
        _note_reason(np_, rest)


def _signal_all(procs, sig):
    for np_ in procs:
        try:
            np_.popen.send_signal(sig)
            np_.signalled = True
        except ProcessLookupError:
            pass


# ------------------------------------------------------------------------------------------ CLI


def cmd_launch(args) -> int:
    graph = _graph.GRAPHS[args.graph]
    texts = {}
    for a in graph.arguments:
        value = getattr(args, a.name, None)
        if value is not None and a.path and value != "":
            value = str(Path(value).resolve())          # nodes log absolute paths
        texts[a.name] = value if value is not None else ""
    try:
        specs = graph.nodes(texts)
    except ValueError as e:
        print(f"uw-sil launch {graph.name}: {e}", file=sys.stderr)
        return 2
    return launch(specs)


def cmd_play(args) -> int:
    params = {"bag": str(args.bag), "rate": float(args.rate), "loop": bool(args.loop)}
    if args.topics:
        params["topics"] = list(args.topics)
    if args.clock:
        params["clock_hz"] = float(args.clock)
    return launch([_graph.NodeSpec("bag_play", "bag_play", parameters=params, required=True)])


def _positive(text: str) -> float:
    v = float(text)
    if not v > 0:
        import argparse

        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def _arg_type(arg: _graph.GraphArg):
    """argparse type: the graph argument's own check (its message names the argument)."""
    import argparse

    def parse(text: str):
        try:
            return arg.parse(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    parse.__name__ = arg.name
    return parse


def add_commands(subparsers) -> None:
    """Register ``launch`` and ``play`` on the ``uw-sil`` argument parser."""
    la = subparsers.add_parser("launch", help="start a ROS 2 node graph (what `ros2 launch` does)",
                               description="Start the nodes of a uw_sil graph as processes, as `ros2 launch` would "
                                           "(launch is not on PyPI). Ctrl-C stops them all. The options are the "
                                           "graph's launch arguments.")
    graphs = la.add_subparsers(dest="graph", metavar="GRAPH", required=True)
    for graph in _graph.GRAPHS.values():
        g = graphs.add_parser(graph.name, help=graph.description, description=graph.description)
        for a in graph.arguments:
            option = "--" + a.name.replace("_", "-")
            if a.kind is bool and a.default is False:
                g.add_argument(option, dest=a.name, action="store_true", help=a.description)
            else:
                g.add_argument(option, dest=a.name, type=_arg_type(a), help=a.help,
                               metavar=a.name.upper() if not a.choices else "{" + ",".join(a.choices) + "}")
        g.set_defaults(func=cmd_launch, graph=graph.name)

    pl = subparsers.add_parser("play", help="replay a bag with its recorded timing (what `ros2 bag play` does)")
    pl.add_argument("bag")
    pl.add_argument("--rate", type=_positive, default=1.0)
    pl.add_argument("--loop", action="store_true")
    pl.add_argument("--topics", nargs="+", help="only these topics")
    pl.add_argument("--clock", type=_positive, help="publish /clock at this rate [Hz]")
    pl.set_defaults(func=cmd_play)
