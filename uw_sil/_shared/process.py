"""Settings of a process that does the array work: its thread budget and its allocator.

- Threads for its own parallel work (θ evaluation of a candidate batch), decided in one place so that
  a campaign running several dives side by side can share the cores: ``UW_SIL_THREADS`` (set by
  :mod:`uw_sil.campaign` in each worker process, or by hand) wins; otherwise up to 2 threads (two
  threads on two cores give ~1.6-1.8x on θ; more help little at these image sizes).
- glibc's allocator: a fixed ``MALLOC_TRIM_THRESHOLD_`` in the environment (Dask's nanny sets 65536
  in every worker) also freezes the mmap threshold at 128 KiB, so every image-sized numpy temporary
  is mmap'ed, page-faulted and unmapped again: a fit ran 2.3x slower in a Dask worker (10.2 s
  against 4.5 s, 320x240, 15 CMA-ES iterations). :func:`prefer_array_malloc` raises both thresholds.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from typing import Optional

ENV = "UW_SIL_THREADS"


def default_threads(requested: Optional[int] = None) -> int:
    """``requested`` if given, else ``$UW_SIL_THREADS``, else min(2, cores); always >= 1."""
    if requested is not None:
        return max(1, int(requested))
    env = os.environ.get(ENV, "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ValueError(f"{ENV} must be a whole number of threads, got {env!r}") from None
    return max(1, min(2, os.cpu_count() or 1))


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3       # glibc <malloc.h>


def prefer_array_malloc(mmap_threshold: int = 64 << 20, trim_threshold: int = 256 << 20) -> bool:
    """Let glibc reuse freed image-sized blocks instead of unmapping them (``mallopt``).

    Returns True when applied; False where there is no glibc (macOS, Windows, musl), where the
    allocator's defaults already adapt. Memory is still returned to the system above ``trim_threshold``.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)))
