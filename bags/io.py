"""Reading and writing rosbag2 MCAP bags with rosbags (ROS 2 Jazzy message types).

A bag on disk is a rosbag2 directory: ``metadata.yaml`` plus one ``<name>.mcap`` file
(storage ``mcap``, metadata version 8, which ``ros2 bag play``/``info`` of Jazzy reads).
A bare ``.mcap`` file can be read as well.

Reading::

    with BagReader("scene_bag") as bag:
        bag.topics["/imu/data"]            # TopicInfo(msgtype, count, offered_qos)
        for raw in bag.messages(["/imu/data"]):   # RawMessage, log-time order
            msg = bag.deserialize(raw)     # rosbags message object

Writing (nothing is left behind if an exception escapes the ``with`` block; the bag is
built in a hidden sibling directory and renamed into place on success; a recorder passes
``keep_partial=True`` to keep what it wrote when the disk fills)::

    with BagWriter("out_bag", overwrite=True) as bag:
        bag.add_topic("/tf_static", "tf2_msgs/msg/TFMessage", qos="latched")
        bag.write("/tf_static", stamp_ns, msg)           # rosbags or rclpy message
        bag.write_raw("/camera/image_raw", stamp_ns, cdr_bytes)

QoS names for ``add_topic`` (recorded in ``offered_qos_profiles``, which ``ros2 bag play``
uses to choose the publisher QoS):

- ``"sensor"``: keep last 5, best effort, volatile (rclcpp/rclpy sensor data profile);
- ``"reliable"``: keep last 10, reliable, volatile;
- ``"latched"``: keep last 1, reliable, transient local (``/tf_static``).

Errors are :mod:`bags.errors` classes with one-line messages naming the path or topic:
:class:`~bags.errors.BagNotFoundError`, :class:`~bags.errors.NotABagError`,
:class:`~bags.errors.CorruptBagError` (truncated or damaged; ``BagReader(path,
recover=True)`` then reads the complete messages before the damage),
:class:`~bags.errors.BagExistsError`, :class:`~bags.errors.BagTopicError`.
"""

from __future__ import annotations

import functools
import os
import shutil
import struct
import sys
import tempfile
import zlib
from collections import defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from types import TracebackType
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import (
    CompressionFormat,
    CompressionMode,
    Reader,
    ReaderError,
    StoragePlugin,
    Writer,
    WriterError,
)
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from bags.errors import (
    BagError,
    BagExistsError,
    BagNotFoundError,
    BagTopicError,
    CorruptBagError,
    NotABagError,
    OutputOverlapError,
)

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: rosbag2 metadata version written (Jazzy's rosbag2 writes and reads version 8).
METADATA_VERSION = 8

_ZERO = QosTime(0, 0)  # rmw "unspecified" duration = the policy default (infinite)


def _qos(depth: int, reliability: QosReliability, durability: QosDurability) -> Qos:
    return Qos(
        QosHistory.KEEP_LAST,
        depth,
        reliability,
        durability,
        _ZERO,
        _ZERO,
        QosLiveliness.AUTOMATIC,
        _ZERO,
        False,
    )


#: The offered QoS profile recorded for each ``add_topic(qos=...)`` name.
QOS_PROFILES: dict[str, Qos] = {
    "sensor": _qos(5, QosReliability.BEST_EFFORT, QosDurability.VOLATILE),
    "reliable": _qos(10, QosReliability.RELIABLE, QosDurability.VOLATILE),
    "latched": _qos(1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL),
}


@functools.cache
def typestore() -> Typestore:
    """The shared rosbags typestore with every ROS 2 Jazzy message type (do not mutate)."""
    return get_typestore(Stores.ROS2_JAZZY)


def serialize(msg: Any, msgtype: str) -> bytes:
    """CDR bytes of ``msg`` (a rosbags or an rclpy message of type ``msgtype``): the one
    serialisation path of the project's bag writers.

    The bytes are a function of the content only: rosbags writes zero alignment padding;
    ``rclpy.serialization.serialize_message`` leaves padding bytes uninitialised, so an
    rclpy message is serialised by rclpy and written again through the typestore (which
    is what makes owl_process's output bytes identical between runs).
    """
    store = typestore()
    if hasattr(msg, "__msgtype__"):  # a rosbags message object
        return bytes(store.serialize_cdr(msg, msgtype))
    from rclpy.serialization import serialize_message

    return bytes(
        store.serialize_cdr(store.deserialize_cdr(serialize_message(msg), msgtype), msgtype)
    )


@dataclass(frozen=True)
class RawMessage:
    """One serialised message as stored in the bag.

    Attributes:
        topic: topic name, e.g. "/imu/data".
        msgtype: ROS 2 type name, e.g. "sensor_msgs/msg/Imu".
        log_time_ns: the bag's log (receive) time, integer nanoseconds.
        data: the CDR bytes exactly as stored (what DDS carries, with encapsulation header).
    """

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes


@dataclass(frozen=True)
class TopicInfo:
    """What a bag holds on one topic.

    Attributes:
        msgtype: ROS 2 type name, e.g. "sensor_msgs/msg/Image".
        count: number of messages on the topic.
        offered_qos: the QoS profiles the recorded publishers offered (may be empty).
    """

    msgtype: str
    count: int
    offered_qos: tuple[Qos, ...]

    @property
    def qos_kind(self) -> str:
        """ "latched" (any publisher transient local), "sensor" (best effort) or "reliable"."""
        if any(q.durability == QosDurability.TRANSIENT_LOCAL for q in self.offered_qos):
            return "latched"
        if any(q.reliability == QosReliability.BEST_EFFORT for q in self.offered_qos):
            return "sensor"
        return "reliable"


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text or type(err).__name__


def _mcap_custom_data(path: Path) -> dict[str, Any]:
    """``custom_data`` of the rosbag2 metadata stored inside an MCAP file, {} if absent."""
    import yaml
    from mcap.reader import make_reader

    try:
        with path.open("rb") as f:
            for record in make_reader(f).iter_metadata():
                if record.name == "rosbag2":
                    meta = yaml.safe_load(record.metadata.get("serialized_metadata", ""))
                    custom = meta.get("custom_data") if isinstance(meta, dict) else None
                    return dict(custom) if isinstance(custom, dict) else {}
    except (McapError, OSError, ValueError, yaml.YAMLError, struct.error):
        return {}
    return {}


def _has_mcap_magic(path: Path) -> bool:
    try:
        with path.open("rb") as f:
            return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def _dataset_hint(folder: Path) -> str:
    """A hint when ``folder`` holds a dataset that owl_import converts ("" otherwise)."""
    asl = (folder / "mav0").is_dir() or (folder.name == "mav0" and (folder / "cam0").is_dir())
    kitti = (folder / "times.txt").is_file() and (folder / "calib.txt").is_file()
    if asl or kitti:
        kind = "an ASL (EuRoC, TUM-VI) folder" if asl else "a KITTI odometry sequence"
        return f" ({kind}: convert it first with owl_import {folder} OUT_BAG)"
    return ""


class BagReader:
    """Reads a rosbag2 directory (metadata.yaml + storage files) or a bare ``.mcap`` file.

    Use as a context manager. Opening raises BagNotFoundError (missing path), NotABagError
    (neither a rosbag2 directory nor an MCAP file) or CorruptBagError (truncated or damaged).
    With ``recover=True`` a damaged or unfinished MCAP (no footer, e.g. a recorder that was
    killed, or a directory without metadata.yaml holding .mcap files) is read up to the
    first damaged record: ``damage`` then says what was wrong, ``messages()`` yields the
    complete messages before it in file order (which is log-time order for bags written in
    time order), and offered QoS come from the MCAP channel records.
    """

    def __init__(self, path: str | os.PathLike[str], *, recover: bool = False) -> None:
        self.path = Path(path)
        self.recover = recover
        #: One-line description of the damage found in recover mode, else None.
        self.damage: str | None = None
        self._reader: Reader | None = None
        self._mcap_files: list[Path] = []
        self._topics: dict[str, TopicInfo] = {}
        self._start_ns = 0
        self._end_ns = 0
        self._store: Typestore = typestore()
        self._msgdefs: dict[str, tuple[str, str]] = {}  # msgtype -> (format, text)
        if not self.path.exists():
            msg = f"bag not found: {self.path}"
            raise BagNotFoundError(msg)
        if self.path.is_dir():
            self._mcap_files = sorted(self.path.glob("*.mcap"))
            if not (self.path / "metadata.yaml").is_file() and not (recover and self._mcap_files):
                msg = f"not a bag: {self.path} is a directory without metadata.yaml"
                raise NotABagError(msg + _dataset_hint(self.path))
        elif not _has_mcap_magic(self.path):
            msg = f"not a bag: {self.path} is neither a rosbag2 directory nor an MCAP file"
            raise NotABagError(msg)
        else:
            self._mcap_files = [self.path]

    # -- opening -------------------------------------------------------------------------

    def open(self) -> None:
        """Read the metadata and indexes (called by ``__enter__``)."""
        try:
            self._open_indexed()
        except CorruptBagError as err:
            if not (self.recover and self._mcap_files):
                raise
            self._open_recovered(str(err))

    def _open_indexed(self) -> None:
        target = self.path
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            # only reached with recover=True: an unfinished recording directory
            if len(self._mcap_files) != 1:
                msg = (
                    f"bag {self.path} has no metadata.yaml and {len(self._mcap_files)} .mcap files"
                )
                raise CorruptBagError(msg)
            target = self._mcap_files[0]
        if target.is_file() and target.suffix != ".mcap":
            # rosbags picks the storage plugin by suffix; recover=True reads it sequentially
            msg = f"cannot index {self.path}: an MCAP file needs the .mcap suffix"
            raise CorruptBagError(msg)
        reader = Reader(target)
        try:
            reader.open()
        except (
            ReaderError, OSError, KeyError, ValueError, TypeError, OverflowError, *_ZSTD_ERRORS
        ) as err:  # fmt: skip
            msg = f"truncated or corrupt bag {self.path}: {_one_line(err)}"
            raise CorruptBagError(msg) from None
        self._reader = reader
        topics: dict[str, TopicInfo] = {}
        for conn in reader.connections:
            qos = tuple(getattr(conn.ext, "offered_qos_profiles", ()) or ())
            old = topics.get(conn.topic)
            if old is not None and old.msgtype != conn.msgtype:
                msg = f"topic {conn.topic} has two types in {self.path}: {old.msgtype}, "
                msg += conn.msgtype
                raise CorruptBagError(msg)
            count = conn.msgcount + (old.count if old else 0)
            topics[conn.topic] = TopicInfo(
                conn.msgtype, count, qos + (old.offered_qos if old else ())
            )
            if conn.msgdef.data:
                fmt = "idl" if conn.msgdef.format.name == "IDL" else "msg"
                self._msgdefs.setdefault(conn.msgtype, (fmt, conn.msgdef.data))
        self._topics = topics
        if reader.message_count:
            self._start_ns = reader.start_time
            self._end_ns = reader.end_time - 1  # rosbags reports end as last + 1
        else:
            self._start_ns = self._end_ns = 0

    def _stream(self) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """Records of every MCAP file in order, stopping (and noting) at the first damage."""
        for file in self._mcap_files:
            schemas: dict[int, Schema] = {}
            channels: dict[int, Channel] = {}
            try:
                with file.open("rb") as f:
                    for record in StreamReader(f, skip_magic=False, validate_crcs=True).records:
                        if isinstance(record, Schema):
                            schemas[record.id] = record
                        elif isinstance(record, Channel):
                            channels[record.id] = record
                        elif isinstance(record, Message) and record.channel_id in channels:
                            channel = channels[record.channel_id]
                            yield schemas.get(channel.schema_id), channel, record
            except (
                McapError, OSError, ValueError, EOFError, OverflowError, struct.error,
                *_ZSTD_ERRORS,
            ) as err:  # fmt: skip
                # garbage record lengths: beyond sys.maxsize, or a short read at the end
                self.damage = f"{file}: {_one_line(err)}"
                return

    def _open_recovered(self, why: str) -> None:
        self.damage = why
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        qos: dict[str, tuple[Qos, ...]] = {}
        start = end = None
        for schema, channel, message in self._stream():
            topic = channel.topic
            if topic not in types:
                types[topic] = schema.name if schema else ""
                text = channel.metadata.get("offered_qos_profiles", "")
                try:
                    qos[topic] = tuple(parse_qos(text)) if text else ()
                except (ValueError, KeyError, TypeError, AttributeError):
                    qos[topic] = ()
                if schema is not None and schema.data:
                    fmt = "idl" if schema.encoding == "ros2idl" else "msg"
                    self._msgdefs.setdefault(schema.name, (fmt, schema.data.decode()))
            counts[topic] = counts.get(topic, 0) + 1
            start = message.log_time if start is None else min(start, message.log_time)
            end = message.log_time if end is None else max(end, message.log_time)
        self._topics = {t: TopicInfo(types[t], counts[t], qos[t]) for t in types}
        self._start_ns = start or 0
        self._end_ns = end or 0

    def close(self) -> None:
        """Release the file handles (called by ``__exit__``)."""
        if self._reader is not None:
            reader, self._reader = self._reader, None
            reader.close()

    def __enter__(self) -> BagReader:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- contents ------------------------------------------------------------------------

    @property
    def topics(self) -> dict[str, TopicInfo]:
        """Topic name -> TopicInfo(msgtype, count, offered_qos)."""
        return dict(self._topics)

    @property
    def start_ns(self) -> int:
        """Log time of the first message, ns (0 for an empty bag)."""
        return self._start_ns

    @property
    def end_ns(self) -> int:
        """Log time of the last message, ns (0 for an empty bag)."""
        return self._end_ns

    @property
    def message_count(self) -> int:
        """Total number of messages."""
        return sum(t.count for t in self._topics.values())

    @property
    def custom_data(self) -> dict[str, str]:
        """metadata.yaml ``custom_data`` (key -> string). A bare .mcap file (or a bag
        without metadata.yaml) gives the copy rosbag2 keeps in the MCAP ``rosbag2``
        metadata record; {} when there is none."""
        custom = {}
        if self._reader is not None:
            custom = getattr(self._reader.storage.metadata, "custom", None) or {}
        if not custom and self._mcap_files:
            custom = _mcap_custom_data(self._mcap_files[0])
        return {str(k): str(v) for k, v in custom.items()}

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        """Yield the messages of ``topics`` (all when None) in log-time order.

        Raises:
            BagTopicError: a requested topic is not in the bag (names it).
            CorruptBagError: a damaged record (a bad chunk checksum included) is met while
                reading; with ``recover=True`` reading stops there instead and ``damage``
                says why.
        """
        wanted = None if topics is None else list(topics)
        if wanted is not None:
            missing = [t for t in wanted if t not in self._topics]
            if missing:
                msg = f"topic {missing[0]} not in bag {self.path} (has: "
                msg += ", ".join(sorted(self._topics)) + ")"
                raise BagTopicError(msg)
        if self._reader is None and not self._topics and self.damage is None:
            msg = f"bag {self.path} is not open (use it as a context manager)"
            raise BagError(msg)
        if self._reader is None:
            keep = None if wanted is None else set(wanted)
            for _schema, channel, message in self._stream():
                if keep is None or channel.topic in keep:
                    yield RawMessage(
                        channel.topic,
                        self._topics[channel.topic].msgtype,
                        message.log_time,
                        bytes(message.data),
                    )
            return
        conns = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        try:
            for conn, stamp, data in self._reader.messages(connections=conns):
                yield RawMessage(conn.topic, conn.msgtype, stamp, bytes(data))
        except (ReaderError, OSError, ValueError, KeyError, OverflowError, *_ZSTD_ERRORS) as err:
            if self.recover:  # keep what came before, say why it stopped
                self.damage = _one_line(err)
                return
            msg = f"truncated or corrupt bag {self.path}: {_one_line(err)}"
            raise CorruptBagError(msg) from None

    def _ensure_type(self, msgtype: str) -> None:
        if msgtype in self._store.fielddefs:
            return
        fmt, text = self._msgdefs.get(msgtype, ("", ""))
        if not text:
            msg = f"message type {msgtype} is not a Jazzy type and the bag has no definition"
            raise BagTopicError(msg)
        if self._store is typestore():
            self._store = get_typestore(Stores.ROS2_JAZZY)  # private copy for custom types
        try:
            types = get_types_from_idl(text) if fmt == "idl" else get_types_from_msg(text, msgtype)
            self._store.register(types)
        except Exception as err:  # rosbags parser errors have no common base
            msg = f"cannot parse the definition of {msgtype} in {self.path}: {_one_line(err)}"
            raise BagTopicError(msg) from None

    def deserialize(self, raw: RawMessage) -> Any:
        """The rosbags message object of ``raw`` (custom types registered from the bag)."""
        self._ensure_type(raw.msgtype)
        try:
            return self._store.deserialize_cdr(raw.data, raw.msgtype)
        except Exception as err:  # CDR decoding errors have no common base class
            msg = f"cannot deserialize {raw.msgtype} on {raw.topic} at {raw.log_time_ns} ns: "
            raise CorruptBagError(msg + _one_line(err)) from None


_OP_CHUNK = 0x06
_OP_DATA_END = 0x0F


def _zstd_errors() -> tuple[type[Exception], ...]:
    """The errors of a damaged zstd chunk (rosbags' zstd module and mcap's zstandard)."""
    found: list[type[Exception]] = [_zstd().ZstdError]
    try:
        import zstandard

        found.append(zstandard.ZstdError)
    except ImportError:  # mcap then cannot read zstd chunks either
        pass
    return tuple(found)


def _zstd() -> Any:
    """The zstd module rosbags itself uses for MCAP chunks."""
    if sys.version_info >= (3, 14):
        from compression import zstd  # type: ignore[import-not-found,unused-ignore]
    else:
        from backports import zstd  # type: ignore[import-not-found,unused-ignore]
    return zstd


def fill_checksums(mcap_path: Path) -> int:
    """Write the CRC-32 checksums that the rosbags MCAP writer leaves at 0 ("not computed").

    Each Chunk record (uncompressed or zstd, as BagWriter writes them) gets the CRC of its
    uncompressed records and the DataEnd record the CRC of the whole data section (the magic
    up to DataEnd), as the MCAP specification defines them; readers (rosbags, ``mcap`` with
    ``validate_crcs``) then detect bytes changed inside a message, not only damaged
    structure. Edits the 4-byte fields in place; the file's size and layout do not change.

    Args:
        mcap_path: a complete MCAP file (magic, records, DataEnd, summary, footer, magic).

    Returns:
        The number of chunks given a checksum.

    Raises:
        CorruptBagError: a record runs past the end of the file.
    """
    chunks = 0
    # One sequential pass, one record in memory at a time (not a mapping of the whole file:
    # its pages would count as resident memory for a multi-GB bag).
    with mcap_path.open("r+b") as f:
        size_total = f.seek(0, os.SEEK_END)
        f.seek(0)
        magic = f.read(len(MCAP_MAGIC))
        data_crc = zlib.crc32(magic)
        pos, end = len(MCAP_MAGIC), size_total - len(MCAP_MAGIC)
        while pos < end:
            head = f.read(9)
            op, length = head[0], int.from_bytes(head[1:9], "little")
            body = pos + 9
            if body + length > end:
                msg = f"{mcap_path}: record at byte {pos} runs past the end of the file"
                raise CorruptBagError(msg)
            if op == _OP_DATA_END:
                f.seek(body)
                f.write(struct.pack("<I", data_crc))
                break
            record = bytearray(f.read(length))
            if op == _OP_CHUNK:
                # start u64, end u64, uncompressed size u64, crc u32, compression (u32
                # length + name), records size u64, records (compressed)
                name_len = int.from_bytes(record[28:32], "little")
                name = bytes(record[32 : 32 + name_len]).decode()
                at = 32 + name_len
                size = int.from_bytes(record[at : at + 8], "little")
                if name == "zstd":  # the checksum is of the uncompressed records
                    crc = zlib.crc32(_zstd().decompress(bytes(record[at + 8 : at + 8 + size])))
                elif not name:
                    crc = zlib.crc32(record[at + 8 : at + 8 + size])
                else:
                    msg = f"{mcap_path}: chunk at byte {pos} has compression {name!r}"
                    raise CorruptBagError(msg)
                record[24:28] = struct.pack("<I", crc)
                f.seek(body + 24)
                f.write(record[24:28])
                f.seek(body + length)
                chunks += 1
            data_crc = zlib.crc32(record, zlib.crc32(head, data_crc))
            pos = body + length
    return chunks


def _looks_like_bag_dir(path: Path) -> bool:
    """True for a directory that only holds rosbag2 files (safe to replace)."""
    allowed = {".mcap", ".db3", ".yaml", ".zstd", ".tmp"}
    entries = list(path.iterdir())
    return all(e.is_file() and e.suffix in allowed for e in entries) and (
        not entries
        or (path / "metadata.yaml").exists()
        or any(e.suffix == ".mcap" for e in entries)
    )


#: The one message for an existing output (every tool exits with status 1 on it).
OVERWRITE_MESSAGE = "output {path} exists (add --overwrite to replace it)"


def _overlap(output: Path, source: Path) -> str | None:
    """How ``output`` overlaps ``source`` ("is", "is inside", "contains"), or None."""
    out, src = output.resolve(), source.resolve()
    if out == src:
        return "is"
    if out.is_relative_to(src):
        return "is inside"
    if src.is_relative_to(out):
        return "contains"
    return None


def _bag_dir_of(source: Path) -> Path | None:
    """The rosbag2 directory that holds ``source`` when it is one of its .mcap files (the
    directory has metadata.yaml or only rosbag2 files), else None."""
    try:
        if source.suffix != ".mcap" or not source.is_file():
            return None
        folder = source.resolve().parent
        if (folder / "metadata.yaml").is_file() or _looks_like_bag_dir(folder):
            return folder
    except OSError:  # unreadable: the overlap with the file itself was checked
        return None
    return None


def check_output(
    output: str | os.PathLike[str],
    inputs: Iterable[str | os.PathLike[str]] = (),
    *,
    overwrite: bool = False,
) -> None:
    """Refuse an output path before a tool reads or renders anything.

    The one check every writing tool shares (owl_process, owl_make_bag, owl_record, the
    demo, the result bags of owl_eval/owl_bench): an output that is one of ``inputs``,
    lies inside one or contains one is refused even with ``overwrite`` (replacing it
    would delete the input); an input named by its ``.mcap`` file counts as its bag
    directory too; an existing output is refused unless ``overwrite``.

    Raises:
        OutputOverlapError: the output is, is inside or contains an input.
        BagExistsError: the output exists and ``overwrite`` is False.
    """
    out = Path(output)
    for source in inputs:
        how = _overlap(out, Path(source))
        if how is not None:
            msg = f"refusing to write {out}: the output {how} the input {source}"
            raise OutputOverlapError(msg)
        bag = _bag_dir_of(Path(source))
        how = None if bag is None else _overlap(out, bag)
        if how is not None:
            msg = f"refusing to write {out}: the output {how} the input bag {bag} (of {source})"
            raise OutputOverlapError(msg)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise BagExistsError(OVERWRITE_MESSAGE.format(path=out))


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` all at once: into a hidden temporary file in the
    same directory, then ``os.replace`` onto ``path``, so that an interrupted or failed
    write leaves the old file (or none) and never a partial one. The temporary file is
    removed on an error.

    Raises:
        OSError: the directory cannot be written (permissions, disk full, ...).
    """
    out = Path(path)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("x", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


_ZSTD_ERRORS = _zstd_errors()


def _os_reason(err: BaseException) -> str:
    """The OS's message of ``err`` ("No space left on device"; the caller names the path)."""
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    return _one_line(err)


def _chunk_extent(index: bytes) -> tuple[int, int, int, dict[int, int]]:
    """(first and last log time, end offset, messages per channel id) of one written chunk,
    from its MCAP ChunkIndex record (which the rosbags writer keeps in memory until close).

    The end offset includes the chunk's message index records, one per channel after the
    chunk record, each 15 bytes of header and 16 bytes a message (rosbags' reader counts
    the messages the same way).
    """
    start, end, offset, length = struct.unpack_from("<QQQQ", index, 0)
    (size,) = struct.unpack_from("<I", index, 32)
    at_channel = sorted((at, cid) for cid, at in struct.iter_unpack("<HQ", index[36 : 36 + size]))
    (index_length,) = struct.unpack_from("<Q", index, 36 + size)
    chunk_end = offset + length + index_length
    bounds = [at for at, _ in at_channel[1:]] + [chunk_end]
    counts = {
        cid: (nxt - at - 15) // 16 for (at, cid), nxt in zip(at_channel, bounds, strict=True)
    }
    return start, end, chunk_end, counts


def _close_quietly(storage: Any) -> None:
    """Close the rosbags MCAP storage's file; what its buffer still held is dropped."""
    bio = getattr(storage, "bio", None)
    if bio is not None and not bio.closed:
        try:
            bio.close()
        except (OSError, ValueError):  # the flush failed; the file is closed anyway
            pass


class BagWriter:
    """Writes a rosbag2 directory (metadata.yaml + <name>.mcap) with the Jazzy typestore.

    The bag is written into a hidden temporary directory next to ``path`` and moved to
    ``path`` when the ``with`` block ends without an exception; on an exception the
    temporary output is deleted and an existing bag at ``path`` stays untouched (with
    ``overwrite`` it is replaced only once the new bag is complete).

    An OS error creating, writing or closing the output (read-only or full disk, I/O
    error) raises BagError naming the bag and the OS's message; nothing more is written
    after it, and the temporary output is deleted unless ``keep_partial``.

    Args:
        path: the output rosbag2 directory.
        overwrite: replace an existing bag at ``path``. Only a directory that holds
            nothing but rosbag2 files is replaced; anything else raises BagExistsError.
        inputs: the paths the tool reads; an output that is one of them, is inside one
            or contains one is refused, even with ``overwrite`` (see check_output).
        compress: zstd-compress the MCAP chunks (deterministic: the same messages give
            the same bytes); False writes them uncompressed.
        keep_partial: for recorders, whose messages cannot be written again: what was
            written is kept. After an OS error ``close()`` (or leaving the ``with`` block)
            finishes the bag with the messages already on disk (the damaged end of the
            MCAP is cut off) or, when even that fails, leaves them at ``path`` as an
            unfinished MCAP that ``BagReader(path, recover=True)`` reads, and raises
            BagError saying how many messages are where. An exception leaving the
            ``with`` block after messages were written also finishes the bag.

    Raises:
        BagExistsError: ``path`` exists and ``overwrite`` is False, or it is not a bag.
        OutputOverlapError: ``path`` is, is inside or contains one of ``inputs``.
        BagError: the output cannot be created or written (the OS's message).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        overwrite: bool = False,
        inputs: Iterable[str | os.PathLike[str]] = (),
        compress: bool = True,
        keep_partial: bool = False,
    ) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.compress = compress
        self.keep_partial = keep_partial
        self.inputs = tuple(Path(p) for p in inputs)
        self._check_target()
        self._tmpdir: Path | None = None
        self._writer: Writer | None = None
        self._storage: Any = None  # the rosbags McapWriter of the open bag
        self._header_end = 0  # where the MCAP's first chunk starts
        self._failure: str | None = None  # the OS error that stopped writing
        self._conns: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self._custom: dict[str, str] = {}
        self.count = 0

    def _error(self, err: BaseException) -> BagError:
        return BagError(f"cannot write bag {self.path}: {_os_reason(err)}")

    def _check_target(self) -> None:
        try:
            self._check_target_path()
        except BagError:
            raise
        except OSError as err:  # e.g. a name too long, a parent that cannot be read
            raise self._error(err) from None

    def _check_target_path(self) -> None:
        check_output(self.path, self.inputs, overwrite=True)
        if not self.path.exists() and not self.path.is_symlink():
            if not self.path.parent.is_dir():
                msg = f"output directory {self.path.parent} does not exist (for bag {self.path})"
                raise BagError(msg)
            return
        if not self.overwrite:
            raise BagExistsError(OVERWRITE_MESSAGE.format(path=self.path))
        if not self.path.is_dir() or self.path.is_symlink() or not _looks_like_bag_dir(self.path):
            msg = f"refusing to overwrite {self.path}: it is not a rosbag2 directory"
            raise BagExistsError(msg)

    def open(self) -> None:
        """Create the temporary output (called by ``__enter__``)."""
        self._check_target()
        try:
            self._tmpdir = Path(
                tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent)
            )
            writer = Writer(
                self._tmpdir / self.path.name,
                version=METADATA_VERSION,
                storage_plugin=StoragePlugin.MCAP,
            )
            if self.compress:
                # zstd MCAP chunks ("storage" compression: metadata.yaml stays uncompressed,
                # as Jazzy's mcap storage plugin writes it with a compression preset)
                writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            writer.open()
            self._storage = writer.storage
            self._header_end = self._storage.bio.tell()
        except (WriterError, OSError) as err:
            self._discard()
            raise self._error(err) from None
        self._writer = writer

    def set_custom_data(self, key: str, value: str) -> None:
        """Record a string in metadata.yaml ``custom_data`` (e.g. scenario options)."""
        self._custom[str(key)] = str(value)

    def add_topic(self, topic: str, msgtype: str, qos: str = "reliable") -> None:
        """Register ``topic`` with ROS 2 type ``msgtype`` and QoS name (see QOS_PROFILES)."""
        if self._writer is None:
            msg = f"bag {self.path} is not open (use BagWriter as a context manager)"
            raise BagError(msg)
        if qos not in QOS_PROFILES:
            msg = f"unknown qos {qos!r} for topic {topic} (choose from {', '.join(QOS_PROFILES)})"
            raise BagTopicError(msg)
        if topic in self._conns:
            msg = f"topic {topic} added twice to bag {self.path}"
            raise BagTopicError(msg)
        if msgtype not in typestore().fielddefs:
            msg = f"message type {msgtype!r} (topic {topic}) is not a ROS 2 Jazzy type"
            raise BagTopicError(msg)
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, typestore=typestore(), offered_qos_profiles=[QOS_PROFILES[qos]]
        )
        self._types[topic] = msgtype

    def _conn(self, topic: str) -> Any:
        conn = self._conns.get(topic)
        if conn is None or self._writer is None:
            msg = f"topic {topic} was not added to bag {self.path} (call add_topic first)"
            raise BagTopicError(msg)
        return conn

    def write_raw(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> None:
        """Store CDR bytes ``data`` on ``topic`` with log time ``stamp_ns`` (int ns)."""
        conn = self._conn(topic)
        if int(stamp_ns) < 0:
            msg = f"negative log time {stamp_ns} ns on topic {topic}"
            raise BagError(msg)
        if self._failure is not None:  # the MCAP stream is broken: write nothing more
            msg = f"cannot write bag {self.path}: {self._failure}"
            raise BagError(msg)
        assert self._writer is not None  # _conn checked it
        try:
            self._writer.write(conn, int(stamp_ns), bytes(data))
        except OSError as err:
            self._failure = _os_reason(err)
            raise self._error(err) from None
        self.count += 1

    def write(self, topic: str, stamp_ns: int, msg: object) -> None:
        """Serialise ``msg`` (a rosbags or an rclpy message) with :func:`serialize` and
        store it."""
        self._conn(topic)
        self.write_raw(topic, stamp_ns, serialize(msg, self._types[topic]))

    def close(self) -> None:
        """Finish the MCAP and metadata.yaml and move the bag to ``path``.

        Raises:
            BagError: the bag cannot be written (with ``keep_partial``: what was kept where).
        """
        if self._writer is None or self._tmpdir is None:
            return
        writer, self._writer = self._writer, None
        for key, value in self._custom.items():
            writer.set_custom_data(key, value)
        if self._failure is not None:
            if self.keep_partial:
                raise self._keep_written(writer, self._failure)
            self._abort_writer(writer)
            self._discard()
            raise BagError(f"cannot write bag {self.path}: {self._failure}")
        bag_dir = self._tmpdir / self.path.name
        try:
            writer.close()
            for mcap_file in bag_dir.glob("*.mcap"):
                fill_checksums(mcap_file)
            self._move_into_place(bag_dir)
        except (WriterError, OSError, BagError) as err:
            if self.keep_partial and self._tmpdir is not None:
                raise self._keep_written(writer, _os_reason(err)) from None
            self._discard()
            raise err if isinstance(err, BagError) else self._error(err) from None
        self._discard()

    def _move_into_place(self, bag_dir: Path) -> None:
        """Rename the finished ``bag_dir`` to ``path``. A bag already there (overwrite) is
        first moved into the temporary directory, deleted with it once the new bag is in
        place, or moved back if that fails: it is never gone before the new one is there."""
        assert self._tmpdir is not None
        previous = None
        if self.path.exists() or self.path.is_symlink():
            self._check_target()
            previous = self._tmpdir / ".previous"
            self.path.rename(previous)
        try:
            bag_dir.rename(self.path)
        except OSError as err:
            if previous is not None:
                try:
                    previous.rename(self.path)
                except OSError:
                    self._tmpdir = None  # it holds the previous bag: keep it
                    msg = f"cannot write bag {self.path}: {_os_reason(err)}; its previous "
                    raise BagError(msg + f"content is now in {previous}") from None
            raise

    def _keep_written(self, writer: Writer, reason: str) -> BagError:
        """After an OS error of a ``keep_partial`` writer: finish the bag with the chunks
        already complete on disk (the pending one too if it can still be written), or else
        cut the MCAP after them and leave it unfinished at ``path``; returns the one-line
        error that says which, and where."""
        storage, tmpdir = self._storage, self._tmpdir
        assert storage is not None and tmpdir is not None
        bag_dir = tmpdir / self.path.name
        mcap = Path(storage.path)
        head = f"cannot write bag {self.path}: {reason}"
        _close_quietly(storage)
        try:
            size = mcap.stat().st_size
        except OSError:
            self._tmpdir = None  # leave everything where it is
            return BagError(f"{head}; what was written is in {bag_dir}")
        kept: list[tuple[Any, tuple[int, int, int, dict[int, int]]]] = []
        for index in storage.chunks:
            extent = _chunk_extent(index.getvalue())
            if extent[2] > size:
                break
            kept.append((index, extent))
        end = kept[-1][1][2] if kept else self._header_end
        pending = len(kept) == len(storage.chunks) and storage.chunk.bio.tell() > 0
        count = -1  # messages in the finished bag (-1: not finished)
        for with_pending in (True, False) if pending else (False,):
            count = -1
            try:
                count = self._finish_at(writer, mcap, end, kept, with_pending)
                fill_checksums(mcap)
                self._move_into_place(bag_dir)
            except (WriterError, OSError, BagError) as err:
                _close_quietly(storage)
                if self._tmpdir is None:  # it holds the previous bag: leave both there
                    return BagError(f"{err}; the recording is in {bag_dir}")
                if count < 0:
                    continue  # not finished: try again without the pending chunk
                return self._leave(bag_dir, f"{head}; the {count} messages are in the bag")
            self._discard()
            return BagError(f"{head}; closed it with the {count} messages written before")
        try:  # the complete chunks, as an unfinished MCAP
            os.truncate(mcap, end)
            for leftover in bag_dir.glob("*.tmp"):
                leftover.unlink()
        except OSError:
            pass
        count = sum(sum(extent[3].values()) for _, extent in kept)
        return self._leave(
            bag_dir,
            f"{head}; the {count} messages written before it are in the unfinished bag",
            " (tools that recover damaged bags, e.g. owl_process, read it)",
        )

    def _finish_at(
        self,
        writer: Writer,
        mcap: Path,
        end: int,
        kept: list[tuple[Any, tuple[int, int, int, dict[int, int]]]],
        with_pending: bool,
    ) -> int:
        """Cut the MCAP at ``end`` (after the ``kept`` chunks), set the rosbags writer's
        state to those chunks (and the pending chunk's messages if ``with_pending``) and
        close it: summary, footer and metadata.yaml. Returns the number of messages.

        This sets attributes of rosbags' MCAP writer that are not its public API (as of
        rosbags 0.11.9, the pinned version); the keep_partial tests exercise it."""
        storage = self._storage
        _close_quietly(storage)
        os.truncate(mcap, end)
        storage.bio = mcap.open("r+b")
        storage.bio.seek(end)
        storage.chunks = [index for index, _ in kept]
        counts = dict.fromkeys(storage.channel_stats, 0)
        first, last = 2**63 - 1, 0
        for _, (start, stop, _, chunk_counts) in kept:
            for cid, n in chunk_counts.items():
                counts[cid] = counts.get(cid, 0) + n
            first, last = min(first, start), max(last, stop)
        chunk = storage.chunk
        if with_pending:
            for cid, msgs in chunk.msgs.items():
                counts[cid] = counts.get(cid, 0) + len(msgs)
            if any(chunk.msgs.values()):
                first = min(first, chunk.message_start_time)
                last = max(last, chunk.message_end_time)
        else:
            storage.chunk = type(chunk)(2**63 - 1, 0, BytesIO(), defaultdict(list))
        storage.channel_stats = dict(counts)
        storage.message_start_time, storage.message_end_time = first, last
        writer.counts = dict(counts)
        writer.min_timestamp, writer.max_timestamp = first, last
        writer.storage = storage
        writer.close()
        return sum(counts.values())

    def _leave(self, bag_dir: Path, text: str, note: str = "") -> BagError:
        """Keep ``bag_dir`` (at ``path`` if nothing is there) and say where it is."""
        where = bag_dir
        if not (self.path.exists() or self.path.is_symlink()):
            try:
                bag_dir.rename(self.path)
                where = self.path
                if self._tmpdir is not None:
                    self._tmpdir.rmdir()
            except OSError:
                pass
        self._tmpdir = None
        return BagError(f"{text} {where}{note}")

    def abort(self) -> None:
        """Drop everything written so far (called by ``__exit__`` on an exception)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            self._abort_writer(writer)
        self._discard()

    @staticmethod
    def _abort_writer(writer: Writer) -> None:
        try:
            writer.abort()
        except Exception:  # the output is deleted anyway
            pass

    def _discard(self) -> None:
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        elif self.keep_partial and (self.count or self._failure is not None):
            self.close()  # a recording cannot be made again: keep it; the exception goes on
        else:
            self.abort()
