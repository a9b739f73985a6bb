"""ROS 2 bags of field trials: read (image, camera_info, pose) samples, raw messages and the recorded transforms.

Layout written by :func:`write_trial` (what ``ros2 bag record`` makes: a rosbag2 directory)::

    write_trial("trial.mcap", ...)   ->  trial/metadata.yaml + trial/trial.mcap
    write_trial("trial.db3", ...)    ->  trial/metadata.yaml + trial/trial.db3
    write_trial("trial", ...)        ->  trial/metadata.yaml + trial/trial.mcap   (storage="mcap")

so ``uw-sil synth --out trial.mcap`` gives a bag that ``ros2 bag play trial`` and ``ros2 bag info
trial`` accept (and, since Iron, ``ros2 bag play trial/trial.mcap``); the suffix of ``--out`` only
picks the storage. Readers here accept a bag directory, its ``metadata.yaml``, or a bare ``.mcap`` /
``.db3`` file, and a bag directory without ``metadata.yaml`` (the recorder died before writing it).

Messages are (de)serialized with ``rosbags`` in CDR, rclpy's wire format, with the message
definitions of ROS 2 Kilted for writing and the bag's own definitions for reading.

Cut-off MCAP files (recorder lost power) are read by :mod:`uw_sil.bags.mcap_recover`, which yields every
complete message; the loss is reported in a :class:`ReadReport` (``.report`` of the iterators
returned here) and logged as a warning. A damaged sqlite3 file is read best-effort: messages are
returned until SQLite reports the damage, which is then recorded in the report (SQLite returns
messages in time order, so what is lost is not necessarily only the end).
"""
from __future__ import annotations

import logging
import re
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np
import yaml

from ..sim.transforms import pose_to_matrix
from .imgmsg import compressed_to_rgb, image_to_rgb
from .mcap_recover import McapFormatError, McapScanReport, iter_mcap, read_mcap_summary
from .records import (CAMERA_INFO_TYPE, COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, POSE_TYPE, STORAGE_SUFFIX, TF_TYPE,
                      BagError, PoseFrom, Sample)
from .stamps import StampSynchronizer, SyncStats, seconds_to_ns
from .tf import TF_TOPICS, TfError, TransformBuffer

__all__ = [
    "TopicInfo", "ReadReport", "BagInfo", "RawMessage", "open_bag", "iter_raw", "iter_messages", "read_samples",
    "resolve_bag_path", "load_tf",
]

log = logging.getLogger(__name__)

_SQLITE_MAGIC = b"SQLite format 3\x00"
_MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a bag: name, message type and number of messages (``None`` if unknown)."""

    name: str
    msgtype: str
    count: int | None


@dataclass
class ReadReport:
    """What reading a bag found, including what was lost in a cut-off recording.

    Attributes
    ----------
    path : str
        The bag (directory or file).
    storage : str
        ``"mcap"`` or ``"sqlite3"``.
    files : list of str
        Storage files read.
    metadata_missing : bool
        A bag directory without ``metadata.yaml`` (typical of a recorder that died).
    truncated : bool
        Some file was cut off or damaged: messages may be missing.
    bytes_total, bytes_unreadable : int
        Size of the MCAP files, and how much of it could not be read (0 for sqlite3).
    expected : dict
        Messages per topic according to the bag's own bookkeeping (``metadata.yaml``, else the MCAP
        summary, else the sqlite3 tables); topics without a count are absent.
    read : dict
        Complete messages read per topic (for sqlite3, only the topics asked for).
    requested : list of str or None
        Topics read (``None``: all).
    errors : list of str
        Problems found, with file offsets where relevant.
    warnings : list of str
        Things that are readable but suspicious (e.g. camera_info with distortion).
    sync : SyncStats or None
        Pairing counters of :func:`read_samples` (images read, matched, dropped and why).
    samples : int
        Samples yielded by :func:`read_samples`.
    finished : bool
        The whole bag was read (the numbers are final).
    skipped : list of (int, int, str)
        Frames of :func:`read_samples` without a pose: (index in the image topic, stamp ns, reason).
    pose_source, camera_source : str
        Where :func:`read_samples` took poses and intrinsics from.
    notes : list of str
        What was done to the data on the way (e.g. frames rectified with the calibration's distortion).
    """

    path: str
    storage: str
    files: list = field(default_factory=list)
    metadata_missing: bool = False
    truncated: bool = False
    bytes_total: int = 0
    bytes_unreadable: int = 0
    expected: dict = field(default_factory=dict)
    read: dict = field(default_factory=dict)
    requested: list | None = None
    errors: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    sync: SyncStats | None = None
    samples: int = 0
    finished: bool = False
    skipped: list = field(default_factory=list)
    pose_source: str = ""
    camera_source: str = ""
    notes: list = field(default_factory=list)

    def skip_summary(self, examples: int = 1) -> str:
        """Skipped frames per reason (reasons grouped by their text before any number), e.g. for messages."""
        groups: dict = {}
        for i, _, why in self.skipped:
            key = re.split(r"[\d(]", why, maxsplit=1)[0].strip()
            groups.setdefault(key, []).append((i, why))
        parts = []
        for items in groups.values():
            eg = "; ".join(f"#{i}: {w}" for i, w in items[:examples])
            parts.append(f"{len(items)} x ({eg})")
        return ", ".join(parts)

    @property
    def lost(self) -> dict:
        """Messages missing per topic (expected minus read), for topics read and with a known count."""
        topics = self.expected if self.requested is None else [t for t in self.requested if t in self.expected]
        out = {}
        for t in topics:
            n = self.expected[t] - self.read.get(t, 0)
            if n > 0:
                out[t] = n
        return out

    def summary(self) -> str:
        """A few human-readable lines."""
        lines = [f"{self.path} ({self.storage}, {len(self.files)} file(s))"]
        if self.metadata_missing:
            lines.append("  metadata.yaml missing: storage files read directly (as `ros2 bag reindex` would)")
        if self.truncated and self.storage == "mcap":
            lines.append(f"  TRUNCATED/DAMAGED: {self.bytes_unreadable} of {self.bytes_total} bytes unreadable")
        elif self.truncated:
            lines.append("  DAMAGED: read until SQLite reported the damage")
        shown = set(self.read) | set(self.expected) if self.requested is None else self.requested
        for t in sorted(shown):
            exp = self.expected.get(t)
            lines.append(f"  {t}: read {self.read.get(t, 0)}" + ("" if exp is None else f" of {exp}"))
        if self.lost:
            lines.append(f"  lost: {self.lost}")
        if self.sync is not None:
            s = self.sync
            lines.append(f"  samples: {self.samples} from {s.received[0]} images ({s.exact} exact stamp matches, "
                         f"{s.dropped} images without partner, {s.forced} decided early)")
        if self.skipped:
            lines.append(f"  frames without a pose ({self.pose_source}): {len(self.skipped)}: {self.skip_summary()}")
        lines += [f"  error: {e}" for e in self.errors] + [f"  warning: {w}" for w in self.warnings]
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


@dataclass
class BagInfo:
    """Contents of a bag, like ``ros2 bag info``.

    ``topics`` maps topic name to :class:`TopicInfo`; times are nanoseconds (bag receive times);
    ``report`` tells whether the bag is cut off or damaged and what was lost.
    """

    path: Path
    storage: str
    files: list
    topics: dict
    start_ns: int | None
    end_ns: int | None
    report: ReadReport

    @property
    def message_count(self) -> int:
        return sum(t.count or 0 for t in self.topics.values())

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    def __str__(self) -> str:
        lines = [f"bag: {self.path}", f"storage: {self.storage} ({', '.join(Path(f).name for f in self.files)})",
                 f"duration: {self.duration_s:.3f} s", f"messages: {self.message_count}"]
        for t in sorted(self.topics.values(), key=lambda x: x.name):
            lines.append(f"  {t.name} [{t.msgtype}] {t.count if t.count is not None else '?'}")
        if self.report.truncated or self.report.metadata_missing:
            lines.append(self.report.summary())
        return "\n".join(lines)


class RawMessage(NamedTuple):
    """A serialized message as stored: topic, type, bag receive time (ns) and CDR bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes | memoryview


# --------------------------------------------------------------------------------------------------
# Locating bag files


@dataclass
class _Layout:
    root: Path
    storage: str
    files: list
    metadata: dict | None


def _split_index(p: Path):
    m = re.search(r"_(\d+)$", p.stem)
    return (p.stem[: m.start()] if m else p.stem, int(m.group(1)) if m else -1, p.name)


def _sniff(p: Path) -> str | None:
    with p.open("rb") as f:
        head = f.read(16)
    if head.startswith(_MCAP_MAGIC):
        return "mcap"
    if head == _SQLITE_MAGIC:
        return "sqlite3"
    return None


def resolve_bag_path(path) -> Path:
    """The bag a path refers to: a bag directory, or a bare ``.mcap``/``.db3`` file.

    ``metadata.yaml`` itself resolves to its directory. ``trial.mcap`` (or ``trial.db3``) that does not
    exist as such but is the storage file of a bag directory ``trial/`` -- exactly what
    ``write_trial("trial.mcap")`` and ``uw-sil synth --out trial.mcap`` make -- resolves to ``trial/``,
    so the name given when writing also works when reading.
    """
    p = Path(path)
    if p.name == "metadata.yaml" and p.is_file():
        return p.parent
    if not p.exists():
        d = p.with_suffix("")
        if p.suffix in (".mcap", ".db3") and (d / p.name).is_file():
            return d
        raise FileNotFoundError(f"{p}: does not exist (expected a bag directory, a .mcap or a .db3 file)")
    return p


def _layout(path) -> _Layout:
    p = resolve_bag_path(path)
    if p.is_dir():
        meta_path = p / "metadata.yaml"
        if meta_path.exists():
            try:
                doc = yaml.safe_load(meta_path.read_text())
                meta = doc["rosbag2_bagfile_information"]
                storage = meta["storage_identifier"]
                rel = list(meta["relative_file_paths"])
            except (yaml.YAMLError, OSError, KeyError, TypeError) as exc:
                raise BagError(f"{meta_path}: not a readable rosbag2 metadata file: {_one_line(exc)}") from None
            if storage not in STORAGE_SUFFIX:
                raise BagError(f"{p}: storage {storage!r} is not supported (supported: mcap, sqlite3)")
            files = [p / Path(x).name for x in rel]
            missing = [str(f) for f in files if not f.exists()]
            if missing:
                raise BagError(f"{p}: metadata.yaml lists storage files that do not exist: {missing}")
            if storage == "mcap" and (meta.get("compression_mode") or "").lower() not in ("", "none"):
                raise BagError(f"{p}: rosbag2-level {meta.get('compression_format')} compression "
                               f"({meta.get('compression_mode')} mode) of MCAP bags is not supported; run "
                               f"`ros2 bag convert` first (MCAP's own chunk compression is supported)")
            return _Layout(p, storage, files, meta)
        found = {s: sorted((f for f in p.iterdir() if f.suffix == suf and f.is_file()), key=_split_index)
                 for s, suf in STORAGE_SUFFIX.items()}
        kinds = [s for s, fs in found.items() if fs]
        if not kinds:
            raise BagError(f"{p}: not a ROS 2 bag: no metadata.yaml and no .mcap or .db3 file in it")
        if len(kinds) > 1:
            raise BagError(f"{p}: no metadata.yaml, and both .mcap and .db3 files in it: pass one file")
        log.warning("%s has no metadata.yaml (recording not closed?): reading its %s file(s) directly", p,
                    kinds[0])
        return _Layout(p, kinds[0], found[kinds[0]], None)
    kind = _sniff(p)
    if kind is None:
        size = p.stat().st_size
        what = "an empty file" if size == 0 else "neither an MCAP nor an SQLite file"
        raise BagError(f"{p}: not a ROS 2 bag: {what} (expected a bag directory, a .mcap or a .db3 file)")
    return _Layout(p, kind, [p], None)


def _metadata_counts(meta: dict | None) -> tuple[dict, dict]:
    """(topic -> type, topic -> count) from metadata.yaml."""
    types, counts = {}, {}
    for entry in (meta or {}).get("topics_with_message_count") or []:
        tm = entry.get("topic_metadata", {})
        if "name" in tm:
            types[tm["name"]] = tm.get("type", "")
            if "message_count" in entry:
                counts[tm["name"]] = int(entry["message_count"])
    return types, counts


# --------------------------------------------------------------------------------------------------
# Types


class _Types:
    """Deserializer using the bag's own message definitions, else ROS 2 Kilted's."""

    def __init__(self):
        from rosbags.typesys import Stores, get_typestore

        self._default = get_typestore(Stores.ROS2_KILTED)
        self._bag = get_typestore(Stores.EMPTY)
        self._seen: set = set()

    def add(self, msgtype: str, encoding: str, definition) -> None:
        key = (msgtype, encoding)
        if not definition or key in self._seen or msgtype in self._bag.types:
            return
        from rosbags.typesys import get_types_from_idl, get_types_from_msg

        text = definition.decode() if isinstance(definition, (bytes, bytearray)) else str(definition)
        try:
            if encoding == "ros2msg":
                typs = get_types_from_msg(text, msgtype)
            elif encoding == "ros2idl":
                typs = {}
                sep = "=" * 80 + "\n"
                if text.startswith(sep + "IDL: "):  # several IDL files, each after a "IDL: name" line
                    for part in text.split(sep)[1:]:
                        typs.update(get_types_from_idl(part.split("\n", 1)[1]))
                else:
                    typs.update(get_types_from_idl(text))
            else:
                raise BagError(f"unknown message definition encoding {encoding!r} for {msgtype}")
            self._bag.register(typs)
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f"cannot use the bag's definition of {msgtype}: {exc}") from None
        self._seen.add(key)

    def deserialize(self, data, msgtype: str):
        store = self._bag if msgtype in self._bag.types else self._default
        if msgtype not in store.types:
            raise BagError(f"no definition of message type {msgtype!r}: not in the bag and not a ROS 2 Kilted type")
        try:
            return store.deserialize_cdr(data, msgtype)
        except Exception as exc:
            raise BagError(f"cannot deserialize a {msgtype} message ({len(data)} bytes): {exc}") from None


# --------------------------------------------------------------------------------------------------
# Reading raw messages


def _merge_mcap(report: ReadReport, r: McapScanReport, stopped_early: bool = False) -> None:
    """Add a file's scan to ``report``. When the reader stopped early, the unread rest of the file is not a
    sign of damage: only damage found so far counts."""
    for t, n in r.messages.items():
        report.read[t] = report.read.get(t, 0) + n
    if not stopped_early:
        report.bytes_unreadable += r.bytes_unreadable
    if (r.truncated and not stopped_early) or r.skipped_chunks or r.errors:   # cut off or damaged: messages lost
        report.truncated = True
    report.errors += [f"{Path(r.path).name}: {e}" for e in r.errors]


def _raw_stream(layout: _Layout, topics, report: ReadReport, types: _Types | None):
    """Yield (topic, msgtype, log_time, data) and keep ``report`` up to date."""
    want = None if topics is None else set(topics)
    if layout.storage == "mcap":
        for f in layout.files:
            r = McapScanReport(str(f))
            early = True
            try:
                for m in iter_mcap(f, want, r):
                    ch = m.channel
                    if not ch.msgtype:
                        raise BagError(f"{f}: topic {ch.topic} has no schema (message type unknown)")
                    if ch.message_encoding != "cdr":
                        raise BagError(f"{f}: topic {ch.topic}: message encoding {ch.message_encoding!r} is not "
                                       f"ROS 2 CDR")
                    if types is not None:
                        types.add(ch.msgtype, ch.schema_encoding, ch.schema_data)
                    yield ch.topic, ch.msgtype, m.log_time, m.data
                early = False
            except McapFormatError as exc:
                raise BagError(str(exc)) from None
            finally:  # also when the reader stops early: the report tells what was read and found so far
                _merge_mcap(report, r, stopped_early=early)
                if (r.truncated and not early) or r.skipped_chunks or r.errors:
                    log.warning("%s is cut off or damaged: read %d complete messages, %d of %d bytes unreadable "
                                "(%s)", f, sum(r.messages.values()), r.bytes_unreadable, r.size, "; ".join(r.errors))
        return
    from rosbags.interfaces import MessageDefinitionFormat

    for unit in _sqlite_units(layout):
        try:
            conns = [c for c in unit.connections if want is None or c.topic in want]
            if types is not None:
                for c in conns:
                    enc = {MessageDefinitionFormat.MSG: "ros2msg", MessageDefinitionFormat.IDL: "ros2idl"}.get(
                        c.msgdef.format)
                    if enc:
                        types.add(c.msgtype, enc, c.msgdef.data)
            if conns:
                try:
                    for c, t, data in unit.messages(conns):
                        report.read[c.topic] = report.read.get(c.topic, 0) + 1
                        yield c.topic, c.msgtype, t, data
                except _sqlite_errors() as exc:
                    report.truncated = True
                    report.errors.append(f"sqlite3 error after {sum(report.read.values())} messages: {exc}")
                    log.warning("%s is damaged: %s; read %d messages", layout.root, exc, sum(report.read.values()))
        finally:
            unit.close()


def _sqlite_units(layout):
    """Open rosbags readers of an sqlite3 bag one at a time (the bag directory's ``Reader`` when it has
    metadata, else one reader per ``.db3`` file); the caller closes each. Open errors -> BagError."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

    units = [Reader(layout.root)] if layout.metadata is not None else [Sqlite3Reader(f) for f in layout.files]
    for unit in units:
        try:
            unit.open()
        except (ReaderError, *_sqlite_errors()) as exc:
            raise BagError(_sqlite_open_error(layout.root, exc)) from None
        yield unit


def _one_line(exc: Exception) -> str:
    """An exception's message on one line; for a YAML syntax error the problem and where it is."""
    mark, problem = getattr(exc, "problem_mark", None), getattr(exc, "problem", None)
    if mark is not None and problem:
        return f"YAML syntax error: {problem} (line {mark.line + 1}, column {mark.column + 1})"
    return " ".join(str(exc).split()) or type(exc).__name__


def _sqlite_errors() -> tuple:
    """Exceptions SQLite raises through rosbags (it uses apsw, and may use the standard module)."""
    import sqlite3

    try:
        import apsw
    except ImportError:  # a rosbags without apsw uses the standard sqlite3 module only
        return (sqlite3.Error,)
    return (sqlite3.Error, apsw.Error)


def _sqlite_open_error(root: Path, exc: Exception) -> str:
    return (f"{root}: cannot open sqlite3 bag: {exc} (a damaged or cut-off sqlite3 file cannot be read here; "
            f"SQLite's own `sqlite3 in.db3 .recover | sqlite3 out.db3` may salvage it)")


def _new_report(layout: _Layout) -> ReadReport:
    rep = ReadReport(str(layout.root), layout.storage, [str(f) for f in layout.files],
                     metadata_missing=layout.root.is_dir() and layout.metadata is None)
    if layout.storage == "mcap":
        rep.bytes_total = sum(f.stat().st_size for f in layout.files)
    return rep


def open_bag(path) -> BagInfo:
    """Topics, types, counts and time span of a bag, and whether it is cut off.

    Parameters
    ----------
    path : str or Path
        Bag directory, its ``metadata.yaml``, or a bare ``.mcap`` / ``.db3`` file.

    Returns
    -------
    BagInfo

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    BagError
        Not a ROS 2 bag (empty, other format, unreadable metadata, missing storage files).

    Notes
    -----
    A properly closed MCAP file is summarized from its summary section; a cut-off one is scanned
    entirely (without deserializing), so the counts are those of the complete messages.
    """
    return _open_layout(_layout(path))


def _open_layout(layout: _Layout) -> BagInfo:
    rep = _new_report(layout)
    meta_types, meta_counts = _metadata_counts(layout.metadata)
    types: dict[str, str] = {}
    counts: dict[str, int] = {}
    start = end = None
    if layout.storage == "mcap":
        stats_counts: dict[str, int] = {}
        stats_complete = True
        for f in layout.files:
            try:
                summ = read_mcap_summary(f)
            except OSError as exc:
                raise BagError(f"{f}: cannot read: {exc}") from None
            if summ is not None:
                for t, ch in summ.channels.items():
                    types[t] = ch.msgtype
                for t, n in summ.counts.items():
                    counts[t] = counts.get(t, 0) + n
                    stats_counts[t] = stats_counts.get(t, 0) + n
                    rep.read[t] = rep.read.get(t, 0) + n
                if any(summ.counts.values()):
                    start = summ.start_ns if start is None else min(start, summ.start_ns)
                    end = summ.end_ns if end is None else max(end, summ.end_ns)
                continue
            stats_complete = False
            r = McapScanReport(str(f))
            t_min = t_max = None
            try:
                for m in iter_mcap(f, None, r):
                    t_min = m.log_time if t_min is None else min(t_min, m.log_time)
                    t_max = m.log_time if t_max is None else max(t_max, m.log_time)
            except McapFormatError as exc:
                raise BagError(str(exc)) from None
            _merge_mcap(rep, r)
            for t, n in r.messages.items():
                counts[t] = counts.get(t, 0) + n
            for t, mt in r.topics.items():
                types[t] = mt
            if t_min is not None:
                start = t_min if start is None else min(start, t_min)
                end = t_max if end is None else max(end, t_max)
        rep.expected = dict(meta_counts) if layout.metadata is not None else (stats_counts if stats_complete else {})
    else:
        from rosbags.rosbag2 import Reader

        for unit in _sqlite_units(layout):
            try:
                for c in unit.connections:
                    types[c.topic] = c.msgtype
                    counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
                md = unit.storage.metadata if isinstance(unit, Reader) else unit.metadata
                if md.message_count:  # rosbags' end_time is one past the last message
                    start = md.start_time if start is None else min(start, md.start_time)
                    end = md.end_time - 1 if end is None else max(end, md.end_time - 1)
            finally:
                unit.close()
        rep.expected = dict(meta_counts) if layout.metadata is not None else dict(counts)
    for t, mt in meta_types.items():
        types.setdefault(t, mt)
    topics = {t: TopicInfo(t, types[t], counts.get(t, 0)) for t in types}
    rep.finished = True
    return BagInfo(layout.root, layout.storage, [str(f) for f in layout.files], topics, start, end, rep)


@contextmanager
def _located(root: Path):
    """Errors found while reading a bag start with the bag's path (``<bag>: <topic> at stamp ...``)."""
    try:
        yield
    except BagError as exc:
        if str(exc).startswith(str(root)):
            raise
        raise BagError(f"{root}: {exc}") from None


class _Stream:
    """An iterator with a :class:`ReadReport` (final once exhausted); usable as a context manager."""

    def __init__(self, gen, report: ReadReport):
        self._gen = gen
        self.report = report

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._gen)

    def close(self) -> None:
        """Stop reading and release the bag files."""
        self._gen.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _check_topics(info: BagInfo, wanted: dict) -> None:
    """``wanted``: topic -> allowed types (empty tuple: any)."""
    if not info.topics:
        raise BagError(f"{info.path}: no topics (empty bag)")
    for topic, allowed in wanted.items():
        if topic not in info.topics:
            have = ", ".join(f"{t.name} [{t.msgtype}]" for t in sorted(info.topics.values(), key=lambda x: x.name))
            raise BagError(f"{info.path}: topic {topic!r} is not in the bag; it has: {have}")
        mt = info.topics[topic].msgtype
        if allowed and mt not in allowed:
            raise BagError(f"{info.path}: topic {topic!r} has type {mt}, expected {' or '.join(allowed)}")


def iter_raw(path, topics=None) -> Iterator[RawMessage]:
    """Serialized messages of a bag in storage order (lazy), with a ``.report``.

    Parameters
    ----------
    path : str or Path
        Bag directory, ``metadata.yaml``, or bare ``.mcap`` / ``.db3`` file.
    topics : str or collection of str, optional
        Only these topics (each must exist in the bag); default all.

    Returns
    -------
    iterator of RawMessage
        ``data`` is the CDR payload exactly as stored (for ``rclpy.serialization``).
    """
    layout = _layout(path)
    info = _open_layout(layout)
    if isinstance(topics, str):
        topics = [topics]
    if topics is not None:
        _check_topics(info, {t: () for t in topics})
    rep = _new_report(layout)
    rep.requested = None if topics is None else list(topics)
    rep.expected = info.report.expected

    def gen():
        for topic, msgtype, t, data in _raw_stream(layout, topics, rep, None):
            yield RawMessage(topic, msgtype, t, data)
        rep.finished = True

    return _Stream(gen(), rep)


def iter_messages(path, topic: str) -> Iterator[tuple]:
    """``(log_time_ns, message)`` of one topic, deserialized with ``rosbags`` (lazy), with a ``.report``.

    ``log_time_ns`` is the bag's receive time; header stamps are in the messages. The message
    objects have the ROS field names (``msg.header.stamp.sec``...), ``uint8[]`` fields are numpy
    arrays.
    """
    layout = _layout(path)
    info = _open_layout(layout)
    _check_topics(info, {topic: ()})
    rep = _new_report(layout)
    rep.requested = [topic]
    rep.expected = info.report.expected
    types = _Types()

    def gen():
        with _located(layout.root):
            for _, msgtype, t, data in _raw_stream(layout, [topic], rep, types):
                yield t, types.deserialize(data, msgtype)
        rep.finished = True

    return _Stream(gen(), rep)


# --------------------------------------------------------------------------------------------------
# Samples


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class _SampleBuilder:
    """Turns paired messages into :class:`Sample` objects: decode, calibrate (rectify), pose."""

    def __init__(self, image_topic, info_topic, pose_from, calibration, check_frames: bool, report: ReadReport,
                 tf_buffer=None, markers=None, aligner=None):
        self.image_topic, self.info_topic = image_topic, info_topic
        self.pose_from = pose_from
        self.pose_topic = pose_from.topic if pose_from.kind == "topic" else None
        self.file_calibration = calibration
        self.check_frames = check_frames
        self.report = report
        self.tf = tf_buffer
        self.markers = markers
        self.aligner = aligner
        self._calibs: dict = {}
        self._rectifiers: dict = {}
        self.marker_poses = 0

    def camera(self, msg, t: int):
        """Calibration of a camera_info message (cached), and its frame."""
        from .camera_yaml import CameraCalibration

        fid = str(msg.header.frame_id)
        key = (int(msg.width), int(msg.height), tuple(float(x) for x in msg.k), tuple(float(x) for x in msg.d),
               str(msg.distortion_model), tuple(float(x) for x in msg.r), tuple(float(x) for x in msg.p))
        calib = self._calibs.get(key)
        if calib is None:
            try:
                calib = CameraCalibration.from_camera_info(msg, source=self.info_topic)
            except ValueError as exc:
                raise BagError(f"{self.info_topic} at stamp {t} ns is not a usable calibration "
                               f"(uncalibrated camera?): {exc}") from None
            if int(msg.binning_x) > 1 or int(msg.binning_y) > 1:
                self.warn(f"{self.info_topic} declares binning {msg.binning_x}x{msg.binning_y}: ignored")
            self._calibs[key] = calib
        return calib, fid

    def pose_msg(self, msg, t: int):
        p, q = msg.pose.position, msg.pose.orientation
        try:
            T = pose_to_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
        except ValueError as exc:
            raise BagError(f"{self.pose_topic} at stamp {t} ns: {exc}") from None
        return T, str(msg.header.frame_id)

    def warn(self, text: str) -> None:
        """Add ``text`` to the report's warnings and log it (once per distinct text)."""
        if text not in self.report.warnings:
            self.report.warnings.append(text)
            log.warning(text)

    def _note(self, text: str) -> None:
        if text not in self.report.notes:
            self.report.notes.append(text)
            log.info(text)

    def _rectify(self, img, calib, t: int):
        if not calib.has_distortion:
            return img
        if any(seg.startswith("image_rect") for seg in self.image_topic.split("/")):
            return img     # image_rect, image_rect_color(/compressed): rectified by image_proc, P is its camera
        r = self._rectifiers.get(id(calib))
        if r is None:
            r = self._rectifiers[id(calib)] = calib.rectifier()
            self._note(f"{calib.source or 'the calibration'} has distortion ({calib.distortion_model}: "
                       f"{np.round(calib.D, 4).tolist()}): frames of {self.image_topic} are rectified (OpenCV, "
                       f"K, D, R -> P) and simulated with P's pinhole")
            if r.outside_fraction > 0.005:
                self.warn(f"rectified frames have {100 * r.outside_fraction:.1f}% of their pixels outside the raw "
                           f"image (P computed with alpha > 0): those repeat the border")
        return r(img)

    def _refine(self, img, cam, T, info):
        """Refine a recorded pose by aligning the rendered panel face with the frame (``refine_pose='ecc'``)."""
        T_new, how = self.aligner.correct(img, cam, T)
        if T_new is None:
            return T, {**info, "refinement": f"none (ECC refinement refused: {how['refused']})"}
        return T_new, {**info, "refinement": "ecc", **how}

    def sample(self, index: int, t: int, image_item, info_item, pose_item):
        """A Sample, or (None, reason) for a frame without a pose."""
        msgtype, img_msg = image_item
        try:
            img = image_to_rgb(img_msg) if msgtype == IMAGE_TYPE else compressed_to_rgb(img_msg)
        except (ValueError, TypeError) as exc:
            raise BagError(f"{self.image_topic} at stamp {t} ns: {exc} (image #{index})") from None
        frame = str(img_msg.header.frame_id)
        if info_item is not None:
            calib, info_frame = info_item
            what = f"{self.info_topic} says"
        else:
            calib, info_frame = self.file_calibration, ""
            what = f"camera calibration {calib.source} is for"
        if (img.shape[1], img.shape[0]) != (calib.width, calib.height):
            raise BagError(f"{self.image_topic} at stamp {t} ns is {img.shape[1]}x{img.shape[0]} but "
                           f"{what} {calib.width}x{calib.height} (image #{index})")
        raw = img
        img = self._rectify(img, calib, t)
        if not img.flags.writeable or not img.flags.c_contiguous:
            img = np.array(img, order="C")
        cam = calib.rectified_camera(frame or info_frame or "camera_optical_frame")
        if self.check_frames and info_frame and frame and info_frame != frame:
            raise BagError(f"frame mismatch at stamp {t} ns: {self.image_topic} is in {frame!r} but "
                           f"{self.info_topic} is in {info_frame!r} (pass check_frames=False to accept it anyway)")
        kind = self.pose_from.kind
        info = {"source": str(self.pose_from)}
        if kind == "topic":
            T, pose_frame = pose_item
            if self.check_frames and frame and pose_frame and pose_frame != frame:
                raise BagError(f"frame mismatch at stamp {t} ns: {self.image_topic} is in {frame!r} but "
                               f"{self.pose_topic} is in {pose_frame!r}; the pose must be T_cam_panel in the image's "
                               f"optical frame (pass check_frames=False to accept it anyway)")
        elif kind == "tf":
            from .tf import TfExtrapolationError

            cam_frame = self.pose_from.camera_frame or frame
            if not cam_frame:
                raise BagError(f"{self.image_topic} has no header.frame_id: name the camera frame in "
                               f"--pose-from tf:CAMERA_FRAME:{self.pose_from.panel_frame}")
            if frame and self.pose_from.camera_frame and frame.lstrip("/") != self.pose_from.camera_frame:
                self.warn(f"{self.image_topic} is in frame {frame!r} but poses are looked up for "
                           f"{self.pose_from.camera_frame!r}: it must be the camera's optical frame (z forward)")
            try:
                T = self.tf.lookup(cam_frame, self.pose_from.panel_frame, t)
            except TfExtrapolationError as exc:
                return None, str(exc)
            if T[2, 3] <= 0:
                return None, (f"the panel origin is behind the camera in {cam_frame!r} (z = {T[2, 3]:.2f} m): is it "
                              f"the optical frame (z forward, REP 103) and not e.g. camera_link (x forward)?")
        else:
            if raw is img:
                mp = self.markers.estimate(img, cam)
            else:       # detect on the recorded frame (sharper), corners mapped into the rectified image
                mp = self.markers.estimate(img, cam, raw_image=raw, raw_to_image=calib.rectify_points)
            if mp.T is None:
                if mp.unexpected_ids and not mp.ids and not self.marker_poses:
                    lay = self.markers.layout
                    raise BagError(f"{self.image_topic} image #{index}: ArUco markers {mp.unexpected_ids} "
                                   f"({lay.dictionary}) found but the marker layout {lay.source} declares ids "
                                   f"{lay.ids}: declare your panel's markers (ids, size, pose) in the .markers.yaml "
                                   f"next to its mesh and pass --model")
                return None, f"markers: {mp.reason}"
            if mp.unexpected_ids:
                self.warn(f"ArUco ids {mp.unexpected_ids} seen in {self.image_topic} are not in the marker layout "
                           f"{self.markers.layout.source}: ignored")
            self.marker_poses += 1
            T = mp.T
            info = mp.as_dict()
        if self.aligner is not None and kind != "markers":
            T, info = self._refine(img, cam, T, info)
        return Sample(t, img, cam, T.copy(), frame or cam.frame_id, index=index, pose_info=info), None


def read_samples(path, image_topic: str = "/camera/image_raw", info_topic: str | None = "/camera/camera_info",
                 pose_topic: str | None = "/panel/pose", max_dt: float = 0.05, info_max_dt: float | None = 1.0,
                 lateness: float = 0.1, queue_size: int = 64, check_frames: bool = True, *, calibration=None,
                 pose_from=None, model=None, marker_layout=None, tf_extrapolation: float = 0.1,
                 tf_max_gap: float = 1.0, refine_pose: str = "none") -> Iterator[Sample]:
    """Time-synchronized samples (image, intrinsics, panel pose) of a bag, read lazily.

    Parameters
    ----------
    path : str or Path
        Bag directory, ``metadata.yaml``, or bare ``.mcap`` / ``.db3`` file; MCAP files that were
        cut off are read up to the last complete message.
    image_topic : str
        ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or ``sensor_msgs/CompressedImage``
        (JPEG, PNG).
    info_topic : str or None
        ``sensor_msgs/CameraInfo``; not read when ``calibration`` is given.
    pose_topic : str or None
        ``geometry_msgs/PoseStamped``: the panel pose in the camera optical frame (the default pose
        source, ``topic:pose_topic``).
    max_dt : float
        Largest |pose stamp - image stamp| in seconds; images without such a pose are dropped.
    info_max_dt : float or None
        The same for camera_info (often slower than the images, or published once): ``None``
        accepts the nearest camera_info however far.
    lateness : float
        Out-of-order tolerance of header stamps within a topic, seconds (see
        :class:`~uw_sil.bags.stamps.StampSynchronizer`).
    queue_size : int
        Most images kept waiting for their partners.
    check_frames : bool
        Require camera_info and pose ``header.frame_id`` to equal the image's (when both are set).
    calibration : CameraCalibration or path, optional
        Intrinsics from a ROS ``camera_calibration`` YAML file instead of ``info_topic``.
    pose_from : str or PoseFrom, optional
        ``topic:/TOPIC``, ``tf:CAMERA_FRAME:PANEL_FRAME`` or ``markers`` (see
        :mod:`uw_sil.bags.source`); default ``topic:pose_topic``.
    model : str or Path, optional
        Panel mesh for ``markers`` (its marker layout and the face rendered to refine the pose);
        default the shipped panel.
    marker_layout : MarkerLayout, optional
        Overrides the layout next to ``model``.
    tf_extrapolation, tf_max_gap : float
        Seconds a tf lookup may lie outside an edge's recording, and the longest recording gap
        interpolated across (see :class:`~uw_sil.bags.tf.TransformBuffer`).
    refine_pose : {'none', 'ecc'}
        ``'ecc'``: refine topic and tf poses by aligning the rendered panel face with each frame
        (:class:`uw_sil.sim.align.FaceAligner`; converges from errors up to ~2-3 cm and ~1.5 deg,
        corrections above 5 deg or 10 % of the range are refused and the recorded pose kept, as
        ``Sample.pose_info['refinement']`` says). Marker poses are always refined this way.

    Returns
    -------
    iterator of Sample
        In image arrival order, with a ``.report`` (:class:`ReadReport`, final once exhausted:
        truncation, losses, pairing counters, frames skipped for lack of a pose and why). Frames
        with distortion in their calibration are rectified (``K, D, R -> P``) and ``Sample.camera``
        is ``P``'s pinhole. ``Sample.index`` is the frame's position in the image topic,
        ``Sample.pose_info`` how its pose was found (for markers: ids, reprojection error).

    Raises
    ------
    FileNotFoundError, BagError
        At the call: not a bag, empty bag, missing topic (the message lists the bag's topics),
        wrong message type, tf frame missing (lists the frames) or tf tree with a gap. While
        iterating: undecodable or unsupported image, image size different from the calibration,
        frame mismatch, invalid calibration or pose, markers found with ids the layout does not
        declare (and none it declares); at the end, when no frame had a pose.
    """
    if refine_pose not in ("none", "ecc"):
        raise ValueError(f"refine_pose must be 'none' or 'ecc', got {refine_pose!r}")
    pf = PoseFrom("topic", topic=pose_topic) if pose_from is None else PoseFrom.parse(pose_from)
    if pf.kind == "topic":
        pose_topic = pf.topic
    if calibration is not None:
        from .camera_yaml import CameraCalibration, load_camera_yaml

        calibration = calibration if isinstance(calibration, CameraCalibration) else load_camera_yaml(calibration)
        info_topic = None
    elif not info_topic:
        raise ValueError("no camera intrinsics: give info_topic or a calibration (camera_calibration YAML)")
    topics = [image_topic] + ([info_topic] if info_topic else []) + ([pose_topic] if pf.kind == "topic" else [])
    if len(set(topics)) != len(topics):
        raise ValueError(f"image, camera_info and pose topics must differ, got {topics}")
    layout = _layout(path)
    info = _open_layout(layout)
    wanted = {image_topic: (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)}
    if info_topic:
        wanted[info_topic] = (CAMERA_INFO_TYPE,)
    if pf.kind == "topic":
        wanted[pose_topic] = (POSE_TYPE,)
    _check_topics(info, wanted)
    if not info.topics[image_topic].count:
        raise BagError(f"{info.path}: topic {image_topic!r} has no messages")
    tf_buffer = markers = None
    if pf.kind == "markers" and marker_layout is None:
        from ..sim.markers import layout_for_model

        marker_layout = layout_for_model(model)       # a missing or bad layout file: fail now
    if pf.kind == "tf":
        with _located(layout.root):
            tf_buffer = load_tf(path, extrapolation_s=tf_extrapolation, max_gap_s=tf_max_gap)
            if pf.camera_frame:
                tf_buffer.chain(pf.camera_frame, pf.panel_frame)    # missing frame / gap: fail now
            else:
                tf_buffer.chain(pf.panel_frame, pf.panel_frame)
    rep = _new_report(layout)
    rep.requested = list(topics)
    rep.expected = info.report.expected
    rep.pose_source = str(pf)
    rep.camera_source = calibration.source if calibration is not None else info_topic
    streams = len(topics)
    sync = StampSynchronizer(streams, max_dt=([info_max_dt] if info_topic else []) + ([max_dt] if pf.kind == "topic"
                                                                                       else []),
                             lateness=lateness, queue_size=queue_size) if streams > 1 else None
    rep.sync = sync.stats if sync is not None else SyncStats.for_streams(1)
    builder_args = (image_topic, info_topic, pf, calibration, check_frames, rep)
    types = _Types()
    index = {t: k for k, t in enumerate(topics)}
    k_info = index.get(info_topic) if info_topic else None
    k_pose = index.get(pose_topic) if pf.kind == "topic" else None

    late_ns = seconds_to_ns(lateness)
    newest = [None] * len(topics)
    went_back: set = set()

    def gen():
        nonlocal markers
        aligner = None
        if pf.kind == "markers":
            from ..sim.markers import MarkerPoseEstimator

            markers = MarkerPoseEstimator(marker_layout, model=model)
        elif refine_pose == "ecc":
            from ..sim.align import FaceAligner

            aligner = FaceAligner(model)
        builder = _SampleBuilder(*builder_args, tf_buffer=tf_buffer, markers=markers, aligner=aligner)
        n_img = 0

        def emit(match_stamp, items):
            s, why = builder.sample(items[0][0], match_stamp, items[0][1],
                                    items[k_info] if k_info is not None else None,
                                    items[k_pose] if k_pose is not None else None)
            if s is None:
                rep.skipped.append((items[0][0], match_stamp, why))
                log.info("%s image #%d skipped: %s", image_topic, items[0][0], why)
            else:
                rep.samples += 1
            return s

        try:
            with _located(layout.root):
                for topic, msgtype, _, data in _raw_stream(layout, topics, rep, types):
                    msg = types.deserialize(data, msgtype)
                    t = _stamp_ns(msg.header.stamp)
                    k = index[topic]
                    if newest[k] is not None and newest[k] - t > late_ns and topic not in went_back:
                        went_back.add(topic)
                        builder.warn(f"{topic}: header stamps go back in time by more than the out-of-order "
                                     f"tolerance ({lateness:g} s; first at stamp {t} ns, "
                                     f"{(newest[k] - t) / 1e9:.3f} s back): such messages may be paired with a "
                                     f"neighbour's partners or dropped")
                    newest[k] = t if newest[k] is None else max(newest[k], t)
                    if k == 0:
                        item = (n_img, (msgtype, msg))
                        n_img += 1
                    elif k == k_info:
                        item = builder.camera(msg, t)
                    else:
                        item = builder.pose_msg(msg, t)
                    if sync is None:
                        rep.sync.received[0] += 1
                        rep.sync.matched += 1
                        s = emit(t, (item,))
                        if s is not None:
                            yield s
                        continue
                    for match in sync.add(k, t, item):
                        s = emit(match.stamp_ns, match.items)
                        if s is not None:
                            yield s
                if sync is not None:
                    for match in sync.flush():
                        s = emit(match.stamp_ns, match.items)
                        if s is not None:
                            yield s
                rep.finished = True
                if rep.samples == 0 and rep.skipped:
                    raise BagError(f"no frame of {image_topic} has a panel pose from {pf}: {len(rep.skipped)} "
                                   f"skipped, {rep.skip_summary()}")
        finally:        # also when the reader stops early (closed stream): what was dropped so far
            for closable in (markers, aligner):
                if closable is not None:
                    closable.close()
            if sync is not None and sync.stats.dropped:
                log.warning("%s: %d of %d images %shad no camera_info/pose within tolerance and were dropped",
                            layout.root, sync.stats.dropped, sync.stats.received[0],
                            "" if rep.finished else "read so far ")

    return _Stream(gen(), rep)


def load_tf(bag, topics=TF_TOPICS, extrapolation_s: float = 0.1, max_gap_s: float = 1.0) -> TransformBuffer:
    """Read the transforms of a bag into a :class:`~uw_sil.bags.tf.TransformBuffer`.

    Parameters
    ----------
    bag : str or Path
        Bag directory, ``metadata.yaml``, or bare ``.mcap`` / ``.db3`` file.
    topics : sequence of str
        ``tf2_msgs/msg/TFMessage`` topics; a topic whose name ends in ``_static`` holds static
        transforms. Topics missing from the bag are skipped; if none is there, :class:`~uw_sil.bags.tf.TfError`.
    extrapolation_s, max_gap_s : float
        See :class:`uw_sil.bags.tf.TransformBuffer`.

    Notes
    -----
    Header stamps (not bag receive times) place the transforms in time. Messages are decoded with the
    bag's own definitions through ``rosbags`` (no ROS installation needed).
    """
    info = open_bag(bag)
    present = [t for t in topics if t in info.topics]
    if not present:
        tf_like = [t.name for t in info.topics.values() if t.msgtype == TF_TYPE]
        hint = f" (TFMessage topics in it: {', '.join(tf_like)})" if tf_like else ""
        raise TfError(f"{info.path}: no {' or '.join(topics)} topic, so no tf pose source{hint}")
    for t in present:
        if info.topics[t].msgtype != TF_TYPE:
            raise TfError(f"{info.path}: topic {t!r} has type {info.topics[t].msgtype}, expected {TF_TYPE}")
    buf = TransformBuffer(extrapolation_s, max_gap_s)
    buf.source = " and ".join(present)
    for t in present:
        static = t.endswith("_static")
        for _, msg in iter_messages(bag, t):
            for ts in msg.transforms:
                stamp = int(ts.header.stamp.sec) * 1_000_000_000 + int(ts.header.stamp.nanosec)
                tr, q = ts.transform.translation, ts.transform.rotation
                buf.add(ts.header.frame_id, ts.child_frame_id, stamp, (tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w),
                        static=static)
    return buf
