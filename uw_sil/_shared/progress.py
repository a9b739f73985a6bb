"""Progress display that suits where it is shown: a live bar on a terminal, plain lines in logs.

tqdm redraws its bar with carriage returns. On a terminal that is what one wants; in a CI log, a
pipe or a file (``uw-sil fit ... 2> fit.log``, a launch file's output) every redraw becomes
noise or one endless line. :func:`progress_bar` gives tqdm's bar only when the stream is a
terminal, and otherwise writes a whole line (ending in a newline, no carriage return) at the first
update, then at most every ``interval`` seconds, and a last one when it is closed.
"""
from __future__ import annotations

import sys
import time
from typing import Callable, Optional, TextIO

__all__ = ["progress_bar", "LineProgress", "LOG_INTERVAL_S"]

#: Seconds between two progress lines when the output is not a terminal.
LOG_INTERVAL_S = 5.0


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):   # no isatty, or a closed stream
        return False


class LineProgress:
    """A progress display as whole lines, for logs: ``desc: n/total unit (p%) k=v, ... elapsed s``.

    The same methods as the part of tqdm used here: :meth:`update`, :meth:`set_postfix`,
    :meth:`close` (and a context manager). ``clock`` is injectable for tests.
    """

    def __init__(self, total: Optional[int], desc: str, unit: str = "it", file: Optional[TextIO] = None,
                 interval: float = LOG_INTERVAL_S, clock: Callable[[], float] = time.monotonic):
        self.total, self.desc, self.unit = total, desc, unit
        self.file = sys.stderr if file is None else file
        self.interval = float(interval)
        self.clock = clock
        self.n = 0
        self.postfix: dict = {}
        self._t0 = clock()
        self._last_time: Optional[float] = None
        self._last_n: Optional[int] = None
        self.closed = False

    def _line(self) -> str:
        count = f"{self.n}/{self.total}" if self.total else f"{self.n}"
        pct = f" ({100.0 * self.n / self.total:.0f}%)" if self.total else ""
        post = "".join(f" {k}={v}" for k, v in self.postfix.items())
        return f"{self.desc}: {count} {self.unit}{pct}{post} {self.clock() - self._t0:.0f} s"

    def _emit(self) -> None:
        self.file.write(self._line() + "\n")
        self.file.flush()
        self._last_time, self._last_n = self.clock(), self.n

    def update(self, n: int = 1) -> None:
        """Advance by ``n``; write a line if this is the first update or ``interval`` has passed."""
        self.n += n
        if self._last_time is None or self.clock() - self._last_time >= self.interval:
            self._emit()

    def set_postfix(self, refresh: bool = False, **kwargs) -> None:
        """Values shown after the count (``best=0.95 evals=120``), from the next line on."""
        self.postfix = {k: v for k, v in kwargs.items()}

    def close(self) -> None:
        """Write the final state (unless it was the last line written)."""
        if self.closed:
            return
        self.closed = True
        if self._last_n != self.n:
            self._emit()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def progress_bar(total: Optional[int], desc: str, unit: str = "it", file: Optional[TextIO] = None,
                 interval: float = LOG_INTERVAL_S):
    """A tqdm bar when ``file`` (default stderr) is a terminal, else a :class:`LineProgress`.

    Parameters
    ----------
    total : int or None
        Steps expected (None: unknown).
    desc, unit : str
        Label and unit of the count.
    file : text stream, optional
        Where to write; default ``sys.stderr``.
    interval : float
        Seconds between lines when ``file`` is not a terminal.

    Returns
    -------
    object
        With ``update(n=1)``, ``set_postfix(**values)``, ``close()``; usable as a context manager.
    """
    file = sys.stderr if file is None else file
    if _is_terminal(file):
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, file=file, leave=True, mininterval=0.1)
    return LineProgress(total, desc, unit=unit, file=file, interval=interval)
