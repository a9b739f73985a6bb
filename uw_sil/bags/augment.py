"""A copy of a bag with derived topics added (e.g. ``/camera/image_enhanced`` next to the recorded inputs).

Every message of the source is copied as stored (serialized CDR, same topic, type and receive time); the
added messages are merged in by receive time, so the output plays back in order. The output has the
layout of :func:`uw_sil.bags.writer.write_trial` (``enhanced.mcap`` -> ``enhanced/enhanced.mcap`` +
``metadata.yaml``) and is written atomically: into a hidden temporary directory beside it, renamed into
place only when complete (an error or Ctrl-C leaves nothing behind).

Message definitions are ROS 2 Kilted's (``rosbags``); source topics of other types cannot be written
with a definition and are left out (listed in the result's ``skipped_topics``).
"""
from __future__ import annotations

import heapq
import os
import shutil
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional

from .reader import iter_raw, open_bag
from .records import ROSBAG2_VERSION, BagError
from .writer import bag_dir_and_storage, looks_like_bag_dir

__all__ = ["AugmentResult", "cdr_header_stamp_ns", "write_augmented_bag"]


@dataclass
class AugmentResult:
    path: Path
    copied: int = 0
    added: int = 0
    skipped_topics: list = field(default_factory=list)


def cdr_header_stamp_ns(data) -> int:
    """``header.stamp`` (ns) of a serialized message whose first field is a ``std_msgs/Header`` (Image,
    CameraInfo, PoseStamped...), read from the CDR bytes without deserializing the message."""
    b = bytes(data[:12])
    if len(b) < 12:
        raise BagError(f"message of {len(b)} bytes is too short to hold a header stamp")
    little = b[1] in (1, 3)                      # encapsulation kind: CDR_LE = 1, PL_CDR_LE = 3
    sec, nsec = struct.unpack("<iI" if little else ">iI", b[4:12])
    return sec * 1_000_000_000 + nsec


def write_augmented_bag(src, out, added: Iterable, added_topics: dict, overwrite: bool = False,
                        storage: Optional[str] = None) -> AugmentResult:
    """Copy ``src`` into a new bag ``out`` with the messages of ``added`` merged in.

    Parameters
    ----------
    src : path
        The recorded bag (any layout :func:`uw_sil.bags.reader.iter_raw` reads).
    out : path
        ``name.mcap`` / ``name.db3`` (bag directory ``name/``) or a directory.
    added : iterable of (log_time_ns, topic, cdr_bytes)
        In non-decreasing receive time; consumed lazily, merged with the source's messages by receive
        time (an added message follows a source message of the same time).
    added_topics : dict
        ``topic -> message type`` of the added topics (they must not exist in the source).
    overwrite : bool
        Replace an existing output bag directory.
    storage : {'mcap', 'sqlite3'}, optional
        Default: from the suffix of ``out``.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    info = open_bag(src)
    bag_dir, storage = bag_dir_and_storage(out, storage)
    if bag_dir.resolve() == Path(info.path).resolve():
        raise ValueError(f"output {bag_dir} is the input bag")
    clash = [t for t in added_topics if t in info.topics]
    if clash:
        raise ValueError(f"the input bag already has {clash}")
    if bag_dir.exists():
        if not overwrite:
            raise FileExistsError(f"{bag_dir} exists (use --force to replace it)")
        if not looks_like_bag_dir(bag_dir):
            raise FileExistsError(f"{bag_dir} exists and holds files that are not bag files: not replacing it")
    ts = get_typestore(Stores.ROS2_KILTED)
    unknown = [t for t in sorted(info.topics) if info.topics[t].msgtype not in ts.types]
    for t, mt in added_topics.items():
        if mt not in ts.types:
            raise ValueError(f"added topic {t}: {mt} is not a ROS 2 Kilted message type")
    keep = [t for t in sorted(info.topics) if t not in unknown]
    result = AugmentResult(bag_dir, skipped_topics=unknown)
    bag_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp_parent = Path(tempfile.mkdtemp(prefix=f".{bag_dir.name}.tmp", dir=bag_dir.parent))
    try:
        tmp = tmp_parent / bag_dir.name
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        with Writer(tmp, version=ROSBAG2_VERSION, storage_plugin=plugin) as w:
            w.set_custom_data("generator", "uw_sil.bags.augment.write_augmented_bag")
            conns = {t: w.add_connection(t, info.topics[t].msgtype, typestore=ts) for t in keep}
            conns.update({t: w.add_connection(t, mt, typestore=ts) for t, mt in added_topics.items()})

            def source():
                with iter_raw(src, keep) as stream:
                    for m in stream:
                        yield m.log_time_ns, 0, m.topic, m.data

            def extra():
                for t, topic, data in added:
                    if topic not in added_topics:
                        raise ValueError(f"added message on undeclared topic {topic}")
                    yield int(t), 1, topic, data

            for t, kind, topic, data in heapq.merge(source(), extra(), key=lambda m: (m[0], m[1])):
                w.write(conns[topic], t, bytes(data))
                if kind:
                    result.added += 1
                else:
                    result.copied += 1
        if bag_dir.exists():
            shutil.rmtree(bag_dir)
        os.replace(tmp, bag_dir)
    finally:
        shutil.rmtree(tmp_parent, ignore_errors=True)
    return result
