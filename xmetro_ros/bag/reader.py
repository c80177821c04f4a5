"""Read MCAP bags (ours and others': the C++ rosbag2, rosbags, Foxglove) as ROS 2 messages, recovering damage.

:class:`BagReader` opens a bare ``.mcap`` or a rosbag2 directory (``metadata.yaml`` with its
``relative_file_paths``; without metadata.yaml, every ``*.mcap`` in name order). Messages are streamed record by
record without relying on the summary, so that:

- a truncated file (recorder killed, disk full) yields every complete message, including those of an uncompressed
  chunk cut in the middle, and the report says how many bytes and which chunk/time range were lost;
- a corrupted chunk (CRC mismatch, undecodable compression) is skipped, the rest is read, and the report says how
  many messages it held (from the message index records that follow it) and their time range;
- messages of types not installed here are skipped with one warning per type and counted in the report.

Messages come in file order (log time order within each chunk as written by rosbag2 and by our writer).
"""

from __future__ import annotations

import logging
import re
import struct
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

import yaml
import zstandard
from mcap.records import Attachment, Channel, Metadata, ReadDataStream, Schema

from .codec import deserialize as deserialize_cdr
from .codec import message_class
from .schema import UnknownTypeError

__all__ = ["BagFormatError", "BagMessage", "BagReader", "BagReport", "LostData"]

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_OP_MESSAGE_INDEX, _OP_ATTACHMENT, _OP_METADATA, _OP_DATA_END = 0x07, 0x09, 0x0C, 0x0F
_REC = struct.Struct("<BQ")
_MSG = struct.Struct("<HIQQ")
_CHUNK = struct.Struct("<QQQI")


def _open_chunk(body: memoryview, hdr: list[int]) -> memoryview:
    """Chunk record body → its uncompressed records, CRC checked, without extra copies; fills ``hdr`` with the
    (start, end) log times as soon as they are parsed."""
    start, end, usize, crc = _CHUNK.unpack_from(body, 0)
    hdr += [start, end]
    (clen,) = struct.unpack_from("<I", body, 28)
    compression = bytes(body[32: 32 + clen]).decode()
    (rlen,) = struct.unpack_from("<Q", body, 32 + clen)
    data = body[40 + clen: 40 + clen + rlen]
    if len(data) != rlen:
        raise ValueError("chunk records overrun the chunk record")
    if compression == "zstd":
        data = memoryview(zstandard.ZstdDecompressor().decompress(data, max_output_size=usize))
    elif compression == "lz4":
        import lz4.frame

        data = memoryview(lz4.frame.decompress(data))
    elif compression:
        raise ValueError(f"unsupported chunk compression {compression!r}")
    if len(data) != usize:
        raise ValueError(f"chunk decompressed to {len(data)} bytes, header says {usize}")
    if crc and zlib.crc32(data) != crc:
        raise ValueError(f"chunk CRC mismatch (stored {crc:#010x}, computed {zlib.crc32(data):#010x})")
    return data


class BagFormatError(ValueError):
    """Not a readable bag: missing/empty file, not MCAP, unsupported encoding, bad metadata.yaml."""


@dataclass
class BagMessage:
    """One message: ``msg`` is the deserialized rclpy message (None when reading raw), ``raw`` its CDR bytes."""

    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    msg: Any
    raw: bytes


@dataclass
class LostData:
    """A part of a file that could not be read."""

    file: str
    offset: int
    length: int  # declared size of the damaged record, bytes
    reason: str
    messages: int | None = None  # known only when message index records survived
    start_ns: int | None = None
    end_ns: int | None = None

    def describe(self) -> str:
        n = "an unknown number of" if self.messages is None else str(self.messages)
        when = "" if self.start_ns is None else f", log times {self.start_ns}..{self.end_ns} ns"
        return (f"{Path(self.file).name} @ byte {self.offset}: record of {self.length} bytes damaged "
                f"({n} messages{when}): {self.reason}")


@dataclass
class BagReport:
    """What a read pass delivered and what it could not."""

    files: list[str] = field(default_factory=list)
    messages: int = 0
    by_topic: Counter = field(default_factory=Counter)
    unknown_types: Counter = field(default_factory=Counter)  # type name → messages skipped
    lost: list[LostData] = field(default_factory=list)
    unfinished_files: list[str] = field(default_factory=list)  # no footer: writer did not close the file
    recovered_from_partial_chunk: int = 0

    @property
    def ok(self) -> bool:
        return not self.lost and not self.unknown_types and not self.unfinished_files

    def describe(self) -> str:
        lines = [f"{self.messages} messages read from {len(self.files)} file(s)"]
        lines += [f"  {t}: {n}" for t, n in sorted(self.by_topic.items())]
        for t, n in sorted(self.unknown_types.items()):
            lines.append(f"skipped {n} messages of unknown type {t}")
        for f in self.unfinished_files:
            lines.append(f"{Path(f).name}: not closed by its writer (no summary/footer)")
        if self.recovered_from_partial_chunk:
            lines.append(f"recovered {self.recovered_from_partial_chunk} messages from a truncated chunk")
        lines += ["lost: " + lost.describe() for lost in self.lost]
        return "\n".join(lines)


def natural_key(path: Path) -> list[Any]:
    """Sort key putting rosbag2's split files ``<name>_2.mcap`` before ``<name>_10.mcap`` (name order would not)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def _bag_files(path: Path) -> list[Path]:
    if not path.exists():
        raise FileNotFoundError(f"bag {path} does not exist")
    if path.is_file():
        return [path]
    meta = path / "metadata.yaml"
    if meta.is_file():
        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            storage = info.get("storage_identifier", "mcap")
            rel = info["relative_file_paths"]
        except (yaml.YAMLError, KeyError, TypeError) as e:
            raise BagFormatError(f"{meta} is not a rosbag2 metadata file: {e!r}") from e
        if storage != "mcap":
            raise BagFormatError(f"{path}: storage {storage!r} is not supported (only mcap)")
        files = [path / Path(r).name for r in rel]
        missing = [str(f) for f in files if not f.exists()]
        if missing:
            raise BagFormatError(f"{path}: files listed in metadata.yaml are missing: {missing}")
        return files
    files = sorted(path.glob("*.mcap"), key=natural_key)
    if not files:
        raise BagFormatError(f"{path} holds neither metadata.yaml nor *.mcap files")
    return files


class BagReader:
    """Read a bag (bare ``.mcap`` file or rosbag2 directory).

    Attributes:
        path: the bag. files: its MCAP files in order. report: :class:`BagReport` of the last (or current) pass.

    Raises:
        FileNotFoundError: no such path. BagFormatError: not a bag (see :class:`BagFormatError`).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.files = _bag_files(self.path)
        for f in self.files:
            with open(f, "rb") as fh:
                head = fh.read(len(MAGIC))
            if not head:
                raise BagFormatError(f"{f} is empty (0 bytes): not an MCAP bag")
            if head != MAGIC[: len(head)] or len(head) < len(MAGIC):
                raise BagFormatError(f"{f} is not an MCAP file (bad magic {head[:8]!r})")
        self.report = BagReport(files=[str(f) for f in self.files])
        self._channels: dict[str, dict[int, Channel]] = {}
        self._schemas: dict[str, dict[int, Schema]] = {}
        self._topics: dict[str, str] | None = None
        self._qos: dict[str, str] = {}
        self._hash: dict[str, str] = {}
        self._records: dict[str, tuple[Channel, Schema | None]] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.attachment_records: dict[str, Attachment] = {}  # name → the whole record (media type, times)

    # -- public API ----------------------------------------------------------------------------------------
    def topics(self) -> dict[str, str]:
        """{topic: type name} over all files (from the summaries; a damaged file is scanned)."""
        if self._topics is None:
            topics: dict[str, str] = {}
            for f in self.files:
                channels, schemas = self._summary_channels(f)
                if channels is None:
                    for _ in self._iter_file(f, BagReport(), topics=None, deserialize=False, want_messages=False):
                        pass
                    channels, schemas = self._channels.get(str(f), {}), self._schemas.get(str(f), {})
                for ch in channels.values():
                    sc = schemas.get(ch.schema_id)
                    topics.setdefault(ch.topic, sc.name if sc else "")
                    self._qos.setdefault(ch.topic, ch.metadata.get("offered_qos_profiles", ""))
                    self._hash.setdefault(ch.topic, ch.metadata.get("topic_type_hash", ""))
                    self._records.setdefault(ch.topic, (ch, sc))
            self._topics = topics
        return dict(self._topics)

    def offered_qos(self, topic: str) -> str:
        """The ``offered_qos_profiles`` YAML stored for ``topic`` ("" when none)."""
        self.topics()
        return self._qos.get(topic, "")

    def topic_type_hash(self, topic: str) -> str:
        self.topics()
        return self._hash.get(topic, "")

    def channel_records(self) -> dict[str, tuple[Channel, Schema | None]]:
        """{topic: (its MCAP channel record, its schema record or None)} over all files, first file first; what a
        copy needs to reproduce a topic exactly (schema text, encodings, channel metadata)."""
        self.topics()
        return dict(self._records)

    def messages(self, topics: Iterable[str] | None = None, *, deserialize: bool = True) -> Iterator[BagMessage]:
        """Iterate over messages (all topics, or those in ``topics``); fills ``self.report`` as it goes.

        With ``deserialize`` (default) ``msg`` is an rclpy message; messages of types not installed here are
        skipped (warning once per type, counted in ``report.unknown_types``). Metadata records and attachments
        met on the way are collected in ``self.metadata`` / ``self.attachments``.
        """
        wanted = None if topics is None else set(topics)
        self.report = BagReport(files=[str(f) for f in self.files])
        for f in self.files:
            yield from self._iter_file(f, self.report, wanted, deserialize, want_messages=True)
        if not self.report.ok:
            log.warning("bag %s: %s", self.path, self.report.describe().replace("\n", "; "))

    def read_all(self, topics: Iterable[str] | None = None, *, deserialize: bool = True) -> list[BagMessage]:
        return list(self.messages(topics, deserialize=deserialize))

    # -- internals -----------------------------------------------------------------------------------------
    def _summary_channels(self, f: Path) -> tuple[dict[int, Channel] | None, dict[int, Schema]]:
        from mcap.reader import make_reader

        try:
            with open(f, "rb") as fh:
                summary = make_reader(fh).get_summary()
        except Exception:  # damaged summary/footer: fall back to scanning
            return None, {}
        if summary is None:
            return None, {}
        return dict(summary.channels), dict(summary.schemas)

    def _iter_file(self, f: Path, report: BagReport, topics: set[str] | None, deserialize: bool,
                   want_messages: bool) -> Iterator[BagMessage]:
        key = str(f)
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        # Seed from the summary when it is intact: it survives a corrupted chunk that held a channel record.
        s_channels, s_schemas = self._summary_channels(f)
        if s_channels:
            channels.update(s_channels)
            schemas.update(s_schemas)
        self._channels[key], self._schemas[key] = channels, schemas
        warned: set[str] = set()
        footer = False
        pending_lost: LostData | None = None  # a corrupted chunk whose message index records may follow

        def deliver(ch_id: int, log_t: int, pub_t: int, data: bytes) -> Iterator[BagMessage]:
            ch = channels.get(ch_id)
            if ch is None:
                report.lost.append(LostData(key, -1, len(data), f"message on unknown channel {ch_id}", 1,
                                            log_t, log_t))
                return
            if topics is not None and ch.topic not in topics:
                return
            sc = schemas.get(ch.schema_id)
            type_name = sc.name if sc else ""
            if ch.message_encoding != "cdr":
                report.unknown_types[f"{type_name} ({ch.message_encoding})"] += 1
                return
            msg = None
            if deserialize:
                try:
                    message_class(type_name)
                except UnknownTypeError as e:
                    if type_name not in warned:
                        warned.add(type_name)
                        log.warning("skipping messages of %s on %s: %s", type_name, ch.topic, e)
                    report.unknown_types[type_name] += 1
                    return
                msg = deserialize_cdr(data, type_name)
            report.messages += 1
            report.by_topic[ch.topic] += 1
            yield BagMessage(ch.topic, type_name, log_t, pub_t, msg, data)

        def records(buf: memoryview, base: int, partial: bool) -> Iterator[tuple[int, int, int, int, bytes]]:
            """Parse records inside a chunk; yields (channel, log, publish, offset, data) of messages."""
            pos, n = 0, len(buf)
            while pos + 9 <= n:
                op, length = _REC.unpack_from(buf, pos)
                if pos + 9 + length > n:
                    if not partial:
                        raise ValueError(f"record at chunk offset {pos} overruns the chunk")
                    return
                body = buf[pos + 9: pos + 9 + length]
                if op == _OP_MESSAGE:
                    ch_id, _seq, log_t, pub_t = _MSG.unpack_from(body, 0)
                    yield ch_id, log_t, pub_t, pos, bytes(body[_MSG.size:])
                elif op == _OP_SCHEMA:
                    sc = Schema.read(ReadDataStream(BytesIO(bytes(body))))
                    schemas[sc.id] = sc
                elif op == _OP_CHANNEL:
                    ch = Channel.read(ReadDataStream(BytesIO(bytes(body))))
                    channels[ch.id] = ch
                pos += 9 + length

        with open(f, "rb") as fh:
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(len(MAGIC))
            pos = len(MAGIC)
            while pos < size:
                if size - pos < 9:
                    report.lost.append(LostData(key, pos, size - pos, "truncated record header at end of file"))
                    break
                op, length = _REC.unpack(fh.read(9))
                if pos + 9 + length > size:
                    yield from self._truncated(fh, key, op, pos, length, size, report, records, deliver,
                                               want_messages)
                    pos = size
                    break
                body = fh.read(length)
                if op != _OP_MESSAGE_INDEX and pending_lost is not None:
                    pending_lost = None
                if op == _OP_CHUNK:
                    hdr: list[int] = []
                    try:
                        data = _open_chunk(memoryview(body), hdr)
                        items = list(records(data, pos, partial=False))
                    except Exception as e:  # CRC mismatch, bad compression, overrunning records
                        pending_lost = LostData(key, pos, 9 + length, f"corrupted chunk: {e}", None,
                                                hdr[0] if hdr else None, hdr[1] if hdr else None)
                        report.lost.append(pending_lost)
                        items = []
                    if want_messages:
                        for ch_id, log_t, pub_t, _off, raw in items:
                            yield from deliver(ch_id, log_t, pub_t, raw)
                elif op == _OP_MESSAGE_INDEX and pending_lost is not None:
                    (n_bytes,) = struct.unpack_from("<I", body, 2)
                    pending_lost.messages = (pending_lost.messages or 0) + n_bytes // 16
                elif op == _OP_MESSAGE:
                    ch_id, _seq, log_t, pub_t = _MSG.unpack_from(body, 0)
                    if want_messages:
                        yield from deliver(ch_id, log_t, pub_t, body[_MSG.size:])
                elif op == _OP_SCHEMA:
                    sc = Schema.read(ReadDataStream(BytesIO(body)))
                    schemas[sc.id] = sc
                elif op == _OP_CHANNEL:
                    ch = Channel.read(ReadDataStream(BytesIO(body)))
                    channels[ch.id] = ch
                elif op == _OP_METADATA:
                    md = Metadata.read(ReadDataStream(BytesIO(body)))
                    self.metadata[md.name] = dict(md.metadata)
                elif op == _OP_ATTACHMENT:
                    try:
                        att = Attachment.read(ReadDataStream(BytesIO(body)))
                        self.attachments[att.name] = att.data
                        self.attachment_records[att.name] = att
                    except Exception as e:
                        report.lost.append(LostData(key, pos, 9 + length, f"corrupted attachment: {e}", 0))
                elif op in (_OP_DATA_END, _OP_FOOTER):
                    footer = True  # the summary section follows; everything it indexes has been read
                    break
                pos += 9 + length
        if not footer:
            report.unfinished_files.append(key)

    def _truncated(self, fh: Any, key: str, op: int, pos: int, length: int, size: int, report: BagReport,
                   records: Any, deliver: Any, want_messages: bool) -> Iterator[BagMessage]:
        """The record at ``pos`` runs past the end of the file: recover what can be, report the rest."""
        avail = fh.read(size - pos - 9)
        if op != _OP_CHUNK:
            report.lost.append(LostData(key, pos, size - pos, f"file truncated inside a record (opcode {op:#x}, "
                                        f"{length} bytes declared, {len(avail)} present)", 1 if op == 5 else 0))
            return
        # Chunk: start u64, end u64, uncompressed_size u64, crc u32, compression str, records_len u64, records
        try:
            start, end, _usize, _crc = struct.unpack_from("<QQQI", avail, 0)
            (clen,) = struct.unpack_from("<I", avail, 28)
            compression = bytes(avail[32: 32 + clen]).decode()
            rec_off = 32 + clen + 8
        except struct.error:
            report.lost.append(LostData(key, pos, size - pos, "file truncated inside a chunk header"))
            return
        recovered = 0
        if compression == "" and len(avail) > rec_off:
            for ch_id, log_t, pub_t, _off, raw in records(memoryview(avail)[rec_off:], pos, partial=True):
                recovered += 1
                if want_messages:
                    yield from deliver(ch_id, log_t, pub_t, raw)
        report.recovered_from_partial_chunk += recovered
        why = "compressed chunk cut short" if compression else "uncompressed chunk cut short"
        report.lost.append(LostData(
            key, pos, 9 + length,
            f"file truncated inside a chunk ({why}; {length} bytes declared, {size - pos - 9} present; "
            f"{recovered} complete messages recovered from it)", None, start, end))

