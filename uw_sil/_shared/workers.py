"""Worker processes for independent pieces of array work that threads cannot share out.

The pure-Python parts of the array work (small simulations, the optimizers' bookkeeping) hold the GIL: two
candidate refits of a diagnosis on two threads ran together only 1.15x faster than one after the other
(640x480 bag, 2 cores). :class:`WorkerPool` runs them in processes instead.

Its workers are plain ``python`` children running :func:`_serve` that talk to the parent over their
standard input and output (length-prefixed pickles; what the work prints goes to standard error):

- nothing is forked: a process that holds DDS or OpenGL threads (a ROS node, a renderer) can use it;
- the parent's ``__main__`` is never imported again in a worker, as :mod:`multiprocessing`'s spawn and
  forkserver methods do (a script without an ``if __name__ == "__main__"`` guard would run again there);
- a worker reads end-of-file when its parent dies, even by SIGKILL, and exits; Ctrl-C is left to the parent,
  which stops the workers.

Each worker gets one thread of the work's budget (``UW_SIL_THREADS=1``, BLAS on one thread). Results do not
depend on which worker computes an item nor on what it computed before, as long as what the work keeps between
items (its caches) does not change values: a diagnosis's documents are the same with one process and two
(uw_sil.fit.diagnose).
"""
from __future__ import annotations

import os
import pickle
import select
import struct
import subprocess
import sys
import traceback
from typing import Callable, Optional, Sequence

from .process import ENV, default_threads

__all__ = ["WorkerPool", "WorkerError"]

_HEADER = struct.Struct("<Q")


class WorkerError(RuntimeError):
    """A worker process ended without an answer (killed, crashed), or its answer could not be read."""


def _send(f, obj) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    f.write(_HEADER.pack(len(data)))
    f.write(data)
    f.flush()


def _read_exact(f, n: int) -> bytes:
    parts, got = [], 0
    while got < n:
        b = f.read(n - got)
        if not b:
            raise EOFError
        parts.append(b)
        got += len(b)
    return b"".join(parts)


def _recv(f):
    (n,) = _HEADER.unpack(_read_exact(f, _HEADER.size))
    return pickle.loads(_read_exact(f, n))


class _Worker:
    def __init__(self, preload: Sequence[str]):
        env = dict(os.environ)
        env[ENV] = "1"
        env["OPENBLAS_NUM_THREADS"] = env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = "1"
        # the same uw_sil as the parent's (a source checkout that is not installed, too). First on the path, in
        # the place ``-m`` and ``-c`` give the working directory: another checkout there would shadow it (a bench
        # run from one checkout with the code of another had its workers refit with the first one's effects)
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        boot = (f"import sys; sys.path[0] = {root!r}; from uw_sil._shared.workers import _serve; "
                f"sys.exit(_serve(sys.argv[1:]))")
        self.proc = subprocess.Popen([sys.executable, "-c", boot, *preload],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        self.task: Optional[int] = None
        self.shared: Optional[int] = None

    def fileno(self) -> int:
        return self.proc.stdout.fileno()

    def submit(self, i: int, fn, item, shared) -> None:
        try:
            if shared[0] != self.shared:               # the shared object once per worker and map
                _send(self.proc.stdin, ("shared", shared))
                self.shared = shared[0]
            _send(self.proc.stdin, ("call", (fn, item)))
        except (BrokenPipeError, OSError) as e:
            raise self._died() from e
        self.task = i

    def result(self):
        try:
            ok, value, text = _recv(self.proc.stdout)
        except EOFError:
            raise self._died() from None
        self.task = None
        if not ok:
            if isinstance(value, BaseException):
                value.add_note(f"in a worker process:\n{text}")
                raise value
            raise WorkerError(f"a worker process failed:\n{text}")
        return value

    def _died(self) -> WorkerError:
        try:
            code = self.proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            code = None
        return WorkerError(f"worker process {self.proc.pid} ended without an answer (exit code {code})")

    def stop(self, kill: bool = False) -> None:
        if self.proc.poll() is None:
            if kill:
                self.proc.kill()
            else:
                try:
                    self.proc.stdin.close()           # end of input: the worker exits
                except OSError:
                    pass
        try:
            self.proc.wait(timeout=None if kill else 10.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for f in (self.proc.stdin, self.proc.stdout):
            try:
                f.close()
            except OSError:
                pass


class WorkerPool:
    """``processes`` worker processes (default: the thread budget, :func:`uw_sil._shared.process.default_threads`;
    fewer than 2: everything runs in the calling process), started on the first :meth:`map` of more than one
    item or by :meth:`start`, kept until :meth:`close`. ``preload``: modules each worker imports when it starts
    (while the parent still works). Use as a context manager: the workers stop on exit (killed on an error)."""

    def __init__(self, processes: Optional[int] = None, preload: Sequence[str] = ()):
        self.processes = default_threads(processes)
        self.preload = tuple(preload)
        self._workers: list = []
        self._shared = (0, None)             # (number, object) of the last shared object handed out

    def start(self) -> "WorkerPool":
        if self.processes > 1 and not self._workers:
            self._workers = [_Worker(self.preload) for _ in range(self.processes)]
        return self

    def map(self, fn: Callable, items, shared=None, interrupt: Optional[Callable] = None,
            done: Optional[Callable] = None, cost: Optional[Sequence[float]] = None) -> list:
        """``[fn(shared, item) for item in items]``, side by side in the workers (``fn``, a module-level
        function, ``shared``, the items and the results must pickle); an item's exception is raised here (the
        first to arrive; the workers are then stopped).

        ``shared`` (what every item needs, e.g. the frames) goes to each worker once, and is the same object for
        the items a worker computes, also in later calls with the same (``is``) object: a worker may keep what
        it built from it (an objective's references) from call to call.

        ``interrupt`` is called here about every 0.1 s while the workers run (it raises to stop them);
        ``done(i, result)`` as each result arrives. ``cost``: the items' expected relative costs; the costliest
        are handed out first, which balances the workers (the results stay in the items' order).
        """
        items = list(items)
        if self.processes < 2 or len(items) < 2:
            out = []
            for i, it in enumerate(items):
                if interrupt is not None:
                    interrupt()
                out.append(fn(shared, it))
                if done is not None:
                    done(i, out[-1])
            return out
        self.start()
        if shared is not self._shared[1]:     # (held here, so that it stays the object the workers have)
            self._shared = (self._shared[0] + 1, shared)
        token = self._shared
        out = [None] * len(items)
        todo = list(range(len(items)))
        if cost is not None:
            todo.sort(key=lambda i: -float(cost[i]))
        try:
            while todo or any(w.task is not None for w in self._workers):
                for w in self._workers:
                    if w.task is None and todo:
                        i = todo.pop(0)
                        w.submit(i, fn, items[i], token)
                busy = [w for w in self._workers if w.task is not None]
                ready, _, _ = select.select(busy, [], [], 0.1)
                for w in ready:
                    i = w.task
                    out[i] = w.result()
                    if done is not None:
                        done(i, out[i])
                if interrupt is not None:
                    interrupt()
        except BaseException:
            self.close(kill=True)
            raise
        return out

    def close(self, kill: bool = False) -> None:
        workers, self._workers = self._workers, []
        for w in workers:
            w.stop(kill=kill)

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(kill=exc_type is not None)


def _serve(preload: Sequence[str]) -> int:
    """The worker's loop until end of input: read ``("shared", (token, obj))`` (kept) or ``("call", (fn, item))``,
    answer the latter with ``(True, fn(obj, item), "")`` or ``(False, exception, traceback)``."""
    import importlib
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)          # the parent stops its workers on Ctrl-C
    inp = sys.stdin.buffer
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")     # the answers' channel
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())      # what the work prints goes to standard error
    sys.stdout = sys.stderr
    from .process import prefer_array_malloc

    prefer_array_malloc()
    for name in preload:
        importlib.import_module(name)
    shared = None
    while True:
        try:
            kind, msg = _recv(inp)
        except EOFError:
            return 0
        if kind == "shared":
            shared = msg[1]
            continue
        fn, item = msg
        try:
            answer = (True, fn(shared, item), "")
        except BaseException as e:          # noqa: BLE001 (handed to the parent, which raises it)
            answer = (False, e, traceback.format_exc())
        try:
            _send(out, answer)
        except (pickle.PicklingError, TypeError, AttributeError) as e:
            _send(out, (False, None, f"the answer could not be pickled: {e}\n{answer[2]}"))
        except BrokenPipeError:
            return 0


if __name__ == "__main__":
    sys.exit(_serve(sys.argv[1:]))
