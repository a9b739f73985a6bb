"""Campaigns: the same per-dive commands (``uw-sil fit``, ``diagnose``, ``enhance``) over many bags.

A campaign is a folder of dives (one ROS 2 bag each) and a results folder::

    results/<dive>/fit.yaml, fit.json, report/       what `uw-sil fit` writes for that bag
    results/<dive>/diagnose.json, ...                 what `uw-sil diagnose` writes (when asked for)
    results/<dive>/log.txt                            everything the dive's commands printed
    results/<dive>/row.json                           the dive's row, written last (its "done" marker)
    results/campaign.parquet, results/campaign.csv    one row per dive

Each dive runs its steps as the ``uw-sil`` command line does (the ``command`` its caller passes,
:func:`uw_sil.cli.main`, with the step's arguments, in a worker process: this module does not import the
command line it serves), so a campaign computes exactly what single commands compute; its
table is read back from the JSON files the steps wrote. Work is handed to any
:class:`concurrent.futures.Executor`: by default a process pool with the ``spawn`` start method (a
process that holds an OpenGL context must not be forked), or a Dask cluster
(``Client(address).get_executor()``, optional extra ``uw-sil[dask]``). There is no scheduler, queue
or RPC of our own.

- Resumable: a dive with a ``row.json`` for the same steps and options is skipped, whether it
  succeeded or failed with a reason (a bad bag fails again); ``retry_failed=True`` redoes the failed
  ones, ``force=True`` all. A dive whose worker died wrote no row and is run again.
- Cores are shared, not oversubscribed: one dive's fit already evaluates θ on up to two threads, so
  a local pool of ``jobs`` workers gives each dive ``cores // jobs`` threads (``UW_SIL_THREADS`` in the
  worker, :mod:`uw_sil._shared.process`); on a cluster ``threads_per_dive`` says it.
- A failing dive (bad bag, no panel visible, ...) never stops the campaign: it becomes a row with
  ``status = 'error'`` and the command's one-line reason.
"""
from __future__ import annotations

import contextlib
import glob as _glob
import hashlib
import io
import json
import os
import socket
import time
from concurrent.futures import Executor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

from ._shared.fileio import atomic_path, write_text_atomic

__all__ = ["COLUMNS", "STEPS", "Dive", "find_dives", "make_executor", "run_campaign", "run_dive", "summary_line",
           "write_table"]

STEPS = ("fit", "diagnose", "enhance")

#: Columns of the campaign table, in order (parameters follow as ``param_<name>``).
COLUMNS = ("dive", "bag", "status", "error", "steps", "frames_used", "theta_before", "theta_after",
           "verdicts", "wall_time_s", "host", "finished_utc")


@dataclass(frozen=True)
class Dive:
    """One dive of a campaign: its name (the results sub-folder) and its bag."""

    name: str
    bag: str


def find_dives(patterns: Sequence[str] | str) -> list[Dive]:
    """Dives from glob patterns (``'dives/**/*.mcap'``, recursive) or bag paths/directories.

    A rosbag2 directory ``d/`` (``d/metadata.yaml``) and its storage file ``d/d.mcap`` are one dive,
    named after the directory; names are made unique (``name``, ``name-2``, ...) in sorted order.
    """
    if isinstance(patterns, (str, os.PathLike)):
        patterns = [str(patterns)]
    bags: list[Path] = []
    for pat in patterns:
        hits = sorted(_glob.glob(str(pat), recursive=True)) if _glob.has_magic(str(pat)) else [str(pat)]
        for h in hits:
            p = Path(h)
            if p.name == "metadata.yaml":
                p = p.parent
            elif p.suffix in (".mcap", ".db3") and (p.parent / "metadata.yaml").exists():
                p = p.parent
            if not p.exists():
                raise FileNotFoundError(f"{p}: no such bag")
            if p.resolve() not in {b.resolve() for b in bags}:
                bags.append(p)
    if not bags:
        raise FileNotFoundError(f"no bags match {' '.join(map(str, patterns))}")
    dives, seen = [], {}
    for b in sorted(bags, key=str):
        stem = b.name[: -len(b.suffix)] if b.suffix in (".mcap", ".db3") else b.name
        n = seen.get(stem, 0) + 1
        seen[stem] = n
        dives.append(Dive(stem if n == 1 else f"{stem}-{n}", str(b)))
    return dives


def _step_argv(step: str, bag: str, out: Path, options: dict) -> list[str]:
    """The ``uw-sil`` arguments of one step of one dive (outputs inside the dive's folder)."""
    seed = ["--seed", str(options.get("seed", 0))]
    if step == "fit":
        argv = ["fit", "--bag", bag, "--out", str(out / "fit.yaml"), "--summary", str(out / "fit.json"), *seed]
        for opt in ("frames", "stride", "optimizer", "max_iter"):
            if options.get(opt) is not None:
                argv += [f"--{opt.replace('_', '-')}", str(options[opt])]
        if options.get("report", True):
            argv += ["--report", str(out / "report")]
        return argv
    if step == "diagnose":
        argv = ["diagnose", "--bag", bag, "--json", str(out / "diagnose.json"),
                "--params-out", str(out / "diagnose.yaml")]
        if options.get("report", True):
            argv += ["--report", str(out / "diagnose")]
        return argv
    if step == "enhance":
        params = out / ("diagnose.yaml" if (out / "diagnose.yaml").exists() else "fit.yaml")
        return ["enhance", "--bag", bag, "--params", str(params), "--out", str(out / "enhanced.mcap")]
    raise ValueError(f"unknown step {step!r}; expected some of {', '.join(STEPS)}")


def _options_key(steps, options) -> str:
    return hashlib.sha1(json.dumps([list(steps), options], sort_keys=True).encode()).hexdigest()[:16]


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _row(dive: Dive, steps, out: Path) -> dict:
    """The table row of a dive, from the files its steps wrote."""
    row = {"dive": dive.name, "bag": dive.bag, "steps": ",".join(steps)}
    fit = _read_json(out / "fit.json")
    if fit:
        row["frames_used"] = len(fit.get("frames", []))
        row["theta_before"] = fit.get("theta_before")
        row["theta_after"] = fit.get("theta_after")
        for k, v in (fit.get("params") or {}).items():
            row[f"param_{k}"] = v
    diag = _read_json(out / "diagnose.json")
    if diag:
        row["verdicts"] = ",".join(v.get("effect", "?") for v in diag.get("verdict", [])) or "none"
    return row


def run_dive(dive: Dive, out_root: str, steps: Sequence[str], options: dict, force: bool = False,
             retry_failed: bool = False, threads: Optional[int] = None, *,
             command: Callable[[list], int]) -> dict:
    """Run the steps of one dive (in a worker process) and return its row; never raises for a dive's fault.

    ``command(argv)`` runs one step as the ``uw-sil`` command line does and returns its exit status
    (:func:`uw_sil.cli.main`; a module-level function, so that it reaches the worker by name).

    Output of the commands goes to ``<out_root>/<dive>/log.txt``; the row is written last to
    ``row.json`` (atomically), which marks the dive complete for a later resume. ``threads`` sets this
    worker process's thread budget (``UW_SIL_THREADS``); results do not depend on it.
    """
    from ._shared.process import ENV, prefer_array_malloc

    if threads is not None:
        os.environ[ENV] = str(max(1, int(threads)))
    # A Dask nanny sets MALLOC_TRIM_THRESHOLD_, which made fits 2.3x slower (uw_sil._shared.process).
    malloc_note = ("MALLOC_TRIM_THRESHOLD_ is set in this worker: raised glibc's mmap/trim thresholds\n"
                   if "MALLOC_TRIM_THRESHOLD_" in os.environ and prefer_array_malloc() else "")

    out = Path(out_root) / dive.name
    key = _options_key(steps, options)
    done = _read_json(out / "row.json")
    if (not force and done and done.get("options_key") == key
            and (done.get("status") == "ok" or not retry_failed)):
        return {**done, "skipped": True}
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    row = {"dive": dive.name, "bag": dive.bag, "status": "ok", "error": "", "steps": ",".join(steps)}
    log = io.StringIO()
    log.write(malloc_note)
    for step in steps:
        argv = _step_argv(step, dive.bag, out, options)
        print(f"$ uw-sil {' '.join(argv)}", file=log)
        try:
            with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
                code = command(argv)
        except SystemExit as e:          # argparse: unknown option or command
            code = e.code if isinstance(e.code, int) else 2
        except Exception as e:           # a bug in a step: the dive fails, the campaign goes on
            print(f"uw-sil {step}: internal error: {type(e).__name__}: {e}", file=log)
            code = 1
        if code:
            lines = [ln for ln in log.getvalue().splitlines() if ln.strip()]
            row.update(status="error", error=f"{step}: " + (lines[-1] if lines else f"exit status {code}"))
            break
    row.update({k: v for k, v in _row(dive, steps, out).items() if k not in row})
    row.update(wall_time_s=round(time.perf_counter() - t0, 2), host=socket.gethostname(),
               finished_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), options_key=key)
    write_text_atomic(out / "log.txt", log.getvalue())
    write_text_atomic(out / "row.json", json.dumps(row, indent=2))
    return {**row, "skipped": False}


def make_executor(spec: str = "local", jobs: Optional[int] = None):
    """An executor for ``spec`` and a function that shuts it down.

    ``'local'``: a process pool of ``jobs`` workers (default: the number of cores) started with
    ``spawn``. ``'dask://HOST:PORT'`` (or ``tcp://``): the executor of a Dask ``distributed`` client
    connected to that scheduler (``pip install 'uw-sil[dask]'``).
    """
    if spec == "local":
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ex = ProcessPoolExecutor(max_workers=jobs or os.cpu_count() or 1, mp_context=multiprocessing.get_context("spawn"))
        return ex, lambda: ex.shutdown(wait=True, cancel_futures=True)
    if spec.startswith(("dask://", "tcp://")):
        try:
            from distributed import Client
        except ImportError:
            raise ValueError("--executor dask://... needs Dask distributed: pip install 'uw-sil[dask]'") from None
        address = "tcp://" + spec.split("://", 1)[1]
        client = Client(address, timeout=30)
        return client.get_executor(), client.close
    raise ValueError(f"--executor must be 'local' or 'dask://HOST:PORT', got {spec!r}")


def run_campaign(dives: Sequence[Dive], out_root, steps: Sequence[str] = ("fit",), options: Optional[dict] = None,
                 executor: Optional[Executor] = None, jobs: Optional[int] = None, force: bool = False,
                 retry_failed: bool = False, progress: Optional[Callable[[int, int, dict], None]] = None,
                 threads_per_dive: Optional[int] = None, *, command: Callable[[list], int]) -> list[dict]:
    """Run every dive on ``executor`` (default: a local spawn process pool), write the table, return the rows.

    ``command``: what runs each step, :func:`uw_sil.cli.main` (see :func:`run_dive`).

    ``progress(done, total, row)`` is called in this process as each dive finishes. ``threads_per_dive``:
    threads each dive may use (default: the cores divided among the local pool's workers; with a given
    ``executor``, the worker's own default).
    """
    steps = tuple(steps)
    unknown = [s for s in steps if s not in STEPS]
    if unknown or not steps:
        raise ValueError(f"--steps must be some of {','.join(STEPS)}, got {','.join(steps) or 'nothing'}")
    names = [d.name for d in dives]
    if len(set(names)) != len(names):
        raise ValueError("dive names must be unique")
    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    options = dict(options or {})
    own, close = (None, None) if executor is not None else make_executor("local", jobs)
    ex = executor or own
    if threads_per_dive is None and executor is None:
        cores = os.cpu_count() or 1
        threads_per_dive = max(1, cores // max(1, min(jobs or cores, len(dives) or 1)))
    rows = {}
    try:
        futures = {ex.submit(run_dive, d, str(out_root), steps, options, force, retry_failed, threads_per_dive,
                             command=command): d
                   for d in dives}
        for n, fut in enumerate(as_completed(futures), 1):
            d = futures[fut]
            try:
                row = fut.result()
            except Exception as e:        # the worker itself died (e.g. killed): the dive is a failed row
                row = {"dive": d.name, "bag": d.bag, "status": "error", "steps": ",".join(steps),
                       "error": f"worker failed: {type(e).__name__}: {e}", "skipped": False}
            rows[d.name] = row
            if progress:
                progress(n, len(dives), row)
    finally:
        if close:
            close()
    ordered = [rows[d.name] for d in dives]
    write_table(ordered, out_root)
    return ordered


def write_table(rows: Sequence[dict], out_root) -> tuple[Path, Path]:
    """``campaign.parquet`` and ``campaign.csv`` (one row per dive), each written atomically."""
    import csv

    import pyarrow as pa
    import pyarrow.parquet as pq

    params = sorted({k for r in rows for k in r if k.startswith("param_")})
    cols = list(COLUMNS) + params
    clean = [{c: r.get(c) for c in cols} for r in rows]
    out_root = Path(out_root)
    pq_path, csv_path = out_root / "campaign.parquet", out_root / "campaign.csv"
    table = pa.Table.from_pylist(clean, schema=pa.schema(
        [(c, pa.float64() if c in ("theta_before", "theta_after", "wall_time_s") or c.startswith("param_")
          else pa.int64() if c == "frames_used" else pa.string()) for c in cols]))
    with atomic_path(pq_path) as tmp:
        pq.write_table(table, tmp)
    with atomic_path(csv_path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols)
            w.writeheader()
            w.writerows(clean)
    return pq_path, csv_path


def summary_line(rows: Sequence[dict]) -> str:
    ok = sum(r.get("status") == "ok" for r in rows)
    skipped = sum(bool(r.get("skipped")) for r in rows)
    failed = len(rows) - ok
    return f"campaign: {len(rows)} dives, {ok} ok ({skipped} already done), {failed} failed"
