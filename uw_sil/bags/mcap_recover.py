"""Sequential, recovering reader of MCAP files (the storage of ROS 2 bags since Iron).

Field recordings get cut off when the recorder loses power: the MCAP file then ends in the middle of
a chunk and has no summary, index or footer. ``rosbags`` refuses such a file ("File end magic is
invalid"), and the ``mcap`` library's stream reader stops with ``EndOfFile`` at the cut chunk,
losing every message in it (rosbags writes 1 MiB chunks: all of a short, small-image recording).
This module reads the file front to back like ``mcap recover`` and yields every message whose record
is complete, including the complete messages inside the cut chunk (uncompressed, zstd or lz4), and
reports where and how the file ends.

Format reference: the MCAP specification, https://mcap.dev/spec (records are
``opcode:u8 length:u64 content``; integers little-endian; strings ``u32 length + UTF-8``).
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

__all__ = ["MAGIC", "McapFormatError", "McapChannel", "McapMessage", "McapScanReport", "McapSummary",
           "iter_mcap", "read_mcap_summary"]

MAGIC = b"\x89MCAP0\r\n"

_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_STATISTICS, _DATA_END = 0x0B, 0x0F
_KNOWN = set(range(0x01, 0x10))
_CHUNK_FIXED = 8 + 8 + 8 + 4  # start, end, uncompressed size, uncompressed crc
_MSG_FIXED = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time


class McapFormatError(ValueError):
    """The file is not an MCAP file at all (wrong magic, empty)."""


class _Short(Exception):
    """A field runs past the end of its record."""


class _Cursor:
    """Bounds-checked little-endian field reader over a bytes-like object."""

    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf, pos: int = 0, end: int | None = None):
        self.buf, self.pos = buf, pos
        self.end = len(buf) if end is None else end

    def take(self, n: int):
        if n < 0 or self.pos + n > self.end:
            raise _Short()
        v = self.buf[self.pos:self.pos + n]
        self.pos += n
        return v

    def u16(self) -> int:
        return struct.unpack_from("<H", self.take(2))[0]

    def u32(self) -> int:
        return struct.unpack_from("<I", self.take(4))[0]

    def u64(self) -> int:
        return struct.unpack_from("<Q", self.take(8))[0]

    def string(self) -> str:
        return bytes(self.take(self.u32())).decode("utf-8")


@dataclass(frozen=True)
class McapChannel:
    """A channel (topic) with its schema, as declared in the file."""

    id: int
    topic: str
    message_encoding: str
    msgtype: str  # schema name, e.g. "sensor_msgs/msg/Image"; "" if the channel has no schema
    schema_encoding: str  # "ros2msg", "ros2idl", ...
    schema_data: bytes


@dataclass(frozen=True)
class McapMessage:
    """One complete message record. ``data`` is a read-only view into the record's buffer."""

    channel: McapChannel
    log_time: int
    publish_time: int
    sequence: int
    data: memoryview


@dataclass
class McapScanReport:
    """What a sequential read of one MCAP file found.

    Attributes
    ----------
    path : str
    size : int
        File size in bytes.
    complete : bool
        The file ends with a valid footer and magic (it was closed properly).
    data_end_seen : bool
        The data section was closed (a DataEnd record was read): every message was written, even
        if the summary after it is damaged.
    good_bytes : int
        Bytes from the start up to the end of the last record that was used (for a cut
        uncompressed chunk: up to the end of its last complete message; for a cut compressed
        chunk: up to the start of that chunk).
    messages : dict
        Complete messages read per topic.
    topics : dict
        Message type (schema name) of every topic declared so far.
    statistics : dict or None
        Message count per topic from the file's Statistics record (only when the summary was read).
    partial_chunks : int
        Cut chunks from which the complete messages were recovered.
    recovered_from_cut : int
        Messages recovered from the cut chunk.
    skipped_chunks : int
        Complete chunks that could not be used (bad CRC, decompression error, malformed records).
    errors : list of str
        Human-readable description of every problem, with file offsets.
    """

    path: str
    size: int = 0
    complete: bool = False
    data_end_seen: bool = False
    good_bytes: int = 0
    messages: dict = field(default_factory=dict)
    topics: dict = field(default_factory=dict)
    statistics: dict | None = None
    partial_chunks: int = 0
    recovered_from_cut: int = 0
    skipped_chunks: int = 0
    errors: list = field(default_factory=list)

    @property
    def truncated(self) -> bool:
        """The file was not closed properly (cut off, or damaged so that reading stopped early)."""
        return not self.complete

    @property
    def bytes_unreadable(self) -> int:
        return self.size - self.good_bytes


class _State:
    """Schemas and channels seen so far in a file."""

    def __init__(self, report: McapScanReport):
        self.report = report
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, McapChannel] = {}

    def schema(self, content) -> None:
        c = _Cursor(content)
        sid = c.u16()
        name, enc = c.string(), c.string()
        data = bytes(c.take(c.u32()))
        self.schemas[sid] = (name, enc, data)

    def channel(self, content) -> None:
        c = _Cursor(content)
        cid, sid = c.u16(), c.u16()
        topic, menc = c.string(), c.string()
        c.take(c.u32())  # metadata map (QoS profiles), not needed here
        if sid != 0 and sid not in self.schemas:
            self.report.errors.append(f"channel {cid} ({topic}) refers to schema {sid}, which is not in the file")
        name, enc, data = self.schemas.get(sid, ("", "", b""))
        self.channels[cid] = McapChannel(cid, topic, menc, name, enc, data)
        self.report.topics[topic] = name


def _parse_message(content, state: _State, offset: int, report: McapScanReport):
    c = _Cursor(content)
    cid = c.u16()
    seq = c.u32()
    log_time, pub_time = c.u64(), c.u64()
    ch = state.channels.get(cid)
    if ch is None:
        report.errors.append(f"message at offset {offset} on unknown channel {cid}: skipped")
        return None
    report.messages[ch.topic] = report.messages.get(ch.topic, 0) + 1
    return ch, log_time, pub_time, seq


def _decompress_partial(compression: str, data) -> bytes:
    """As much of a cut compressed stream as can be decoded."""
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompressobj().decompress(bytes(data))
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor().decompress(bytes(data))
    raise ValueError(f"unsupported chunk compression {compression!r}")


def _decompress(compression: str, data, size: int) -> bytes:
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(bytes(data))
    raise ValueError(f"unsupported chunk compression {compression!r}")


def _chunk_records(buf, state: _State, topics, report: McapScanReport, where: str, partial: bool):
    """Yield messages of a chunk's (possibly cut) records; return bytes consumed by complete records."""
    pos, n = 0, len(buf)
    while pos < n:
        if pos + 9 > n:
            if not partial:
                report.errors.append(f"{where}: malformed records (cut record header at {pos})")
            return pos
        op = buf[pos]
        length = struct.unpack_from("<Q", buf, pos + 1)[0]
        if pos + 9 + length > n:
            if not partial:
                report.errors.append(f"{where}: malformed records (record at {pos} runs past the chunk)")
            return pos
        content = buf[pos + 9:pos + 9 + length]
        try:
            if op == _SCHEMA:
                state.schema(content)
            elif op == _CHANNEL:
                state.channel(content)
            elif op == _MESSAGE:
                meta = _parse_message(content, state, pos, report)
                if meta is not None and (topics is None or meta[0].topic in topics):
                    yield McapMessage(meta[0], meta[1], meta[2], meta[3], content[_MSG_FIXED:])
        except (_Short, UnicodeDecodeError):
            report.errors.append(f"{where}: malformed record (opcode {op:#04x}) at {pos}")
            return pos
        pos += 9 + length
    return pos


def iter_mcap(path, topics=None, report: McapScanReport | None = None) -> Iterator[McapMessage]:
    """Yield every complete message of an MCAP file, in file order, recovering cut files.

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file.
    topics : collection of str, optional
        Only yield messages of these topics (all messages are still counted in the report).
    report : McapScanReport, optional
        Filled in while reading; final once the iterator is exhausted.

    Yields
    ------
    McapMessage

    Raises
    ------
    McapFormatError
        The file is empty or does not start with the MCAP magic.

    Notes
    -----
    Nothing is raised for a cut or damaged file: reading stops at the first record that is cut or
    malformed (without the index, nothing after it can be located reliably) and the report says
    where. Complete chunks with a wrong CRC or that fail to decompress are skipped and reported.
    Only the records of the data section are yielded; the summary section is read for its
    Statistics record.
    """
    path = Path(path)
    report = report if report is not None else McapScanReport(str(path))
    report.path = str(path)
    topics = None if topics is None else set(topics)
    state = _State(report)
    with path.open("rb") as f:
        size = report.size = path.stat().st_size
        if size == 0:
            raise McapFormatError(f"{path}: empty (0 bytes), not an MCAP file")
        if f.read(8) != MAGIC:
            raise McapFormatError(f"{path}: does not start with the MCAP magic, not an MCAP file")
        pos = report.good_bytes = 8
        in_summary = False
        while True:
            head = f.read(9)
            if len(head) < 9:
                where = "at" if not head else "inside a record header at"
                report.errors.append(f"file ends {where} offset {pos} without a footer (cut off)")
                break
            op = head[0]
            length = struct.unpack_from("<Q", head, 1)[0]
            if op not in _KNOWN and op < 0x80:  # 0x80-0xff are user opcodes, skipped like unknown records
                report.errors.append(f"invalid record opcode {op:#04x} at offset {pos}: the remaining "
                                     f"{size - pos} bytes are unreadable")
                break
            remaining = size - pos - 9
            if length > remaining:
                if op == _CHUNK and not in_summary:
                    yield from _cut_chunk(f.read(remaining), pos, state, topics, report)
                else:
                    report.errors.append(f"record (opcode {op:#04x}) at offset {pos} is cut off: it needs "
                                         f"{length} bytes, the file has {remaining} left")
                break
            if op == _CHUNK and not in_summary:
                yield from _full_chunk(f.read(length), pos, state, topics, report)
            elif op in (_SCHEMA, _CHANNEL, _STATISTICS, _FOOTER) or (op == _MESSAGE and not in_summary):
                content = memoryview(f.read(length))
                try:
                    if op == _SCHEMA:
                        state.schema(content)
                    elif op == _CHANNEL:
                        state.channel(content)
                    elif op == _STATISTICS:
                        report.statistics = _statistics(content, state)[0]
                    elif op == _MESSAGE:
                        meta = _parse_message(content, state, pos, report)
                        if meta is not None and (topics is None or meta[0].topic in topics):
                            yield McapMessage(meta[0], meta[1], meta[2], meta[3], content[_MSG_FIXED:])
                except (_Short, UnicodeDecodeError):
                    report.errors.append(f"malformed record (opcode {op:#04x}) at offset {pos}: the rest of the "
                                         f"file is not read")
                    break
                if op == _FOOTER:
                    pos += 9 + length
                    report.good_bytes = pos
                    if pos + 8 == size and f.read(8) == MAGIC:
                        report.complete = True
                        report.good_bytes = size
                    else:
                        report.errors.append(f"the footer at offset {pos - 9 - length} is not followed by the "
                                             f"closing magic at the end of the file")
                    break
            else:
                if op == _DATA_END:
                    report.data_end_seen = True
                    in_summary = True
                f.seek(length, 1)
            pos += 9 + length
            report.good_bytes = pos
    return report


def _statistics(content, state: _State) -> tuple[dict, int, int]:
    """(message count per topic, first log time, last log time) of a Statistics record."""
    c = _Cursor(content)
    c.u64()  # message count
    c.u16(), c.u32(), c.u32(), c.u32(), c.u32()  # schema, channel, attachment, metadata, chunk counts
    start, end = c.u64(), c.u64()
    n = c.u32() // 10
    out: dict[str, int] = {}
    for _ in range(n):
        cid, count = c.u16(), c.u64()
        ch = state.channels.get(cid)
        topic = ch.topic if ch is not None else f"<channel {cid}>"
        out[topic] = out.get(topic, 0) + count
    return out, start, end


@dataclass(frozen=True)
class McapSummary:
    """Topics, types and counts of a properly closed MCAP file, from its summary section."""

    channels: dict  # topic -> McapChannel
    counts: dict  # topic -> message count
    start_ns: int
    end_ns: int


def read_mcap_summary(path) -> McapSummary | None:
    """Read the summary section of a properly closed MCAP file without reading its messages.

    Returns ``None`` when the file has no usable summary (cut off, no footer, no Statistics
    record, or anything malformed): then :func:`iter_mcap` has to scan the whole file.
    """
    path = Path(path)
    size = path.stat().st_size
    foot = 9 + 20
    if size < 8 + foot + 8:
        return None
    try:
        with path.open("rb") as f:
            if f.read(8) != MAGIC:
                return None
            f.seek(size - 8 - foot)
            tail = f.read(foot + 8)
            if tail[-8:] != MAGIC or tail[0] != _FOOTER or struct.unpack_from("<Q", tail, 1)[0] != 20:
                return None
            summary_start = struct.unpack_from("<Q", tail, 9)[0]
            if not 8 <= summary_start <= size - 8 - foot:
                return None
            f.seek(summary_start)
            buf = memoryview(f.read(size - 8 - foot - summary_start))
        state = _State(McapScanReport(str(path)))
        stats = None
        pos = 0
        while pos < len(buf):
            if pos + 9 > len(buf):
                return None
            op = buf[pos]
            length = struct.unpack_from("<Q", buf, pos + 1)[0]
            if pos + 9 + length > len(buf):
                return None
            content = buf[pos + 9:pos + 9 + length]
            if op == _SCHEMA:
                state.schema(content)
            elif op == _CHANNEL:
                state.channel(content)
            elif op == _STATISTICS:
                stats = _statistics(content, state)
            pos += 9 + length
    except (_Short, UnicodeDecodeError, OSError):
        return None
    if stats is None or state.report.errors:
        return None
    counts, start, end = stats
    channels = {ch.topic: ch for ch in state.channels.values()}
    for topic in channels:
        counts.setdefault(topic, 0)
    if any(t not in channels for t in counts):
        return None
    return McapSummary(channels, counts, start, end)


def _chunk_header(c: _Cursor):
    c.take(16)  # message start / end time
    usize, crc = c.u64(), c.u32()
    comp = c.string()
    rlen = c.u64()
    return usize, crc, comp, rlen


def _full_chunk(content: bytes, pos: int, state: _State, topics, report: McapScanReport):
    where = f"chunk at offset {pos}"
    c = _Cursor(content)
    try:
        usize, crc, comp, rlen = _chunk_header(c)
        records = c.take(rlen)
    except (_Short, UnicodeDecodeError):
        report.errors.append(f"{where}: malformed chunk header, skipped")
        report.skipped_chunks += 1
        return
    try:
        buf = records if comp == "" else _decompress(comp, records, usize)
    except Exception as exc:  # corrupt payload or codec error: skip this chunk, keep reading
        report.errors.append(f"{where}: cannot decompress ({comp}): {exc}; chunk skipped")
        report.skipped_chunks += 1
        return
    if crc != 0 and zlib.crc32(buf) != crc:
        report.errors.append(f"{where}: CRC mismatch; chunk skipped")
        report.skipped_chunks += 1
        return
    yield from _chunk_records(memoryview(buf), state, topics, report, where, partial=False)


def _cut_chunk(content: bytes, pos: int, state: _State, topics, report: McapScanReport):
    where = f"cut chunk at offset {pos}"
    c = _Cursor(content)
    try:
        _, _, comp, _ = _chunk_header(c)
    except (_Short, UnicodeDecodeError):
        report.errors.append(f"{where}: the file ends inside the chunk header ({len(content)} bytes of it)")
        return
    start = c.pos
    try:
        buf = content[start:] if comp == "" else _decompress_partial(comp, content[start:])
    except Exception as exc:
        report.errors.append(f"{where}: cannot decompress the cut {comp} data: {exc}")
        return
    n_before = sum(report.messages.values())
    used = yield from _chunk_records(memoryview(buf), state, topics, report, where, partial=True)
    n_got = sum(report.messages.values()) - n_before
    report.partial_chunks += 1
    report.recovered_from_cut += n_got
    if comp == "":
        report.good_bytes = pos + 9 + start + used
    report.errors.append(f"{where}: the file ends inside this chunk; recovered {n_got} complete messages from it")
