"""Recover a killed recording: rewrite every completed message into a complete, indexed bag (``xmetro bag recover``).

A recorder killed with SIGKILL (or a full disk, a power cut) leaves MCAP files without summary and footer, maybe
ending inside a chunk. Readers that need the summary (``rosbags``, rosbag2's ``ros2 bag``, the ``mcap`` library's
indexed reader) cannot open them ("File end magic is invalid"), and rosbag2 wrote no ``metadata.yaml`` yet. This is
what ``mcap recover`` and ``ros2 bag reindex`` do, in one step:

- every file is read by :class:`~.reader.BagReader`, which does not need the summary: every message of every
  complete chunk, plus the complete messages at the start of an uncompressed chunk cut short; a corrupted chunk is
  skipped and reported;
- the messages are written with :class:`~.writer.BagWriter` in rosbag2's format (schemas and channels as in the
  source: same schema text, ``offered_qos_profiles`` normalised to version 9, ``topic_type_hash``; log and publish
  times kept), with summary, chunk and message indexes, statistics and the ``rosbag2`` metadata record; the source's
  other metadata records (e.g. ``xmetro_manifest``) and attachments are copied;
- a rosbag2 directory (or a bare file recovered into a directory) gets ``metadata.yaml`` (version 9).

Output: IN a file → OUT ``*.mcap`` (one file) or OUT a directory (a rosbag2 directory holding ``<IN name>``); IN a
directory → OUT a directory with one recovered file per source file (same names). The source is never modified.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .reader import MAGIC, BagFormatError, BagReader, BagReport, natural_key
from .writer import BagWriteError, BagWriter, rosbag2_metadata, rosbag2_yaml

__all__ = ["FileRecovery", "RecoverResult", "chunk_compression", "recover"]

_OP_CHUNK, _OP_FOOTER, _OP_DATA_END = 0x06, 0x02, 0x0F


@dataclass
class FileRecovery:
    """One source file: where it went and what its reader delivered/lost."""

    source: str
    output: str | None  # None: nothing readable (skipped)
    messages: int = 0
    report: BagReport | None = None
    note: str = ""


@dataclass
class RecoverResult:
    """What ``recover`` did: per file the messages recovered per topic and what was lost."""

    output: Path
    files: list[FileRecovery] = field(default_factory=list)
    metadata_yaml: Path | None = None

    @property
    def messages(self) -> int:
        return sum(f.messages for f in self.files)

    def describe(self) -> str:
        lines = []
        for f in self.files:
            if f.output is None:
                lines.append(f"{Path(f.source).name}: skipped ({f.note})")
                continue
            rep = f.report
            was = "unfinished (no summary)" if rep and rep.unfinished_files else "complete"
            lines.append(f"{Path(f.source).name} ({was}) → {f.output}: {f.messages} messages")
            if rep is not None:
                lines += [f"  {t}: {n}" for t, n in sorted(rep.by_topic.items())]
                if rep.recovered_from_partial_chunk:
                    lines.append(f"  {rep.recovered_from_partial_chunk} of them from a chunk cut short")
                lines += [f"  lost: {lost.describe()}" for lost in rep.lost]
                lines += [f"  skipped {n} messages of {t}" for t, n in sorted(rep.unknown_types.items())]
        if self.metadata_yaml is not None:
            lines.append(f"wrote {self.metadata_yaml}")
        lines.append(f"{self.messages} messages recovered into {self.output}")
        return "\n".join(lines)


def chunk_compression(path: Path) -> str | None:
    """The compression of the first chunk of an MCAP file ("zstd", "lz4", "" for none; None: no chunk found).

    Walks record headers only (seeks over bodies), so it is cheap on big files and safe on truncated ones.
    """
    with open(path, "rb") as fh:
        fh.seek(0, 2)
        size = fh.tell()
        pos = len(MAGIC)
        while pos + 9 <= size:
            fh.seek(pos)
            op, length = struct.unpack("<BQ", fh.read(9))
            if op in (_OP_FOOTER, _OP_DATA_END):
                return None
            if op == _OP_CHUNK:
                head = fh.read(32)
                if len(head) < 32:
                    return None
                (clen,) = struct.unpack_from("<I", head, 28)
                name = fh.read(clen)
                return name.decode("utf-8", "replace") if len(name) == clen else None
            pos += 9 + length
    return None


def _recover_file(src: Path, dst: Path, compression: str | None, chunk_size: int) -> tuple[FileRecovery, Any]:
    """Copy every readable message of ``src`` into the new bare file ``dst``; returns (summary, the closed writer)."""
    reader = BagReader(src)
    records = reader.channel_records()
    if compression == "auto":
        comp = chunk_compression(src)
        compression = "zstd" if comp == "zstd" else None  # (an lz4 source is rewritten uncompressed: zstd only)
    writer = BagWriter(dst, compression=compression, chunk_size=chunk_size)
    done = FileRecovery(str(src), str(dst))
    try:
        for topic, (ch, sc) in records.items():
            if ch.message_encoding != "cdr" or sc is None:
                continue  # not a ROS 2 channel: the reader skips (and reports) its messages too
            writer.add_topic(topic, sc.name, ch.metadata.get("offered_qos_profiles", ""),
                             schema=(sc.encoding, sc.data), topic_type_hash=ch.metadata.get("topic_type_hash", ""))
        for m in reader.messages(deserialize=False):
            if m.topic not in writer.topics:  # a channel first seen after the summary read (damaged file)
                rec = reader.channel_records().get(m.topic)
                ch2, sc2 = rec if rec is not None else (None, None)
                writer.add_topic(m.topic, m.type_name, ch2.metadata.get("offered_qos_profiles", "") if ch2 else None,
                                 schema=(sc2.encoding, sc2.data) if sc2 else ("ros2msg", b""),
                                 topic_type_hash=ch2.metadata.get("topic_type_hash", "") if ch2 else "")
            writer.write(m.topic, m.raw, m.log_time_ns, m.publish_time_ns)
        for name, data in reader.metadata.items():
            if name != "rosbag2":  # regenerated by the writer for the recovered content
                writer.add_metadata(name, data)
        for att in reader.attachment_records.values():
            writer.add_attachment(att.name, att.data, att.media_type, att.log_time)
    finally:
        writer.close()
    done.messages = writer.message_count
    done.report = reader.report
    return done, writer


def recover(src: str | Path, dst: str | Path, *, compression: str | None = "auto",
            chunk_size: int = 1024 * 1024) -> RecoverResult:
    """Recover the bag ``src`` (bare ``.mcap`` or rosbag2 directory) into the new bag ``dst`` (see module doc).

    Args:
        compression: "auto" (as the source's first chunk: zstd stays zstd), None/"none" or "zstd".
        chunk_size: bytes per chunk in the output.

    Raises:
        FileNotFoundError: no ``src``. FileExistsError: ``dst`` exists (a directory: exists and is not empty).
        ValueError: ``src`` and ``dst`` are the same, or a file cannot be recovered into ``dst``'s form.
        BagFormatError: ``src`` is not an MCAP bag (no readable file). BagWriteError: writing failed.
    """
    src, dst = Path(src), Path(dst)
    if compression == "none":
        compression = None
    if not src.exists():
        raise FileNotFoundError(f"bag {src} does not exist")
    if src.resolve() == dst.resolve():
        raise ValueError("the output must be a new path (the source is never modified)")
    if src.is_dir() and dst.suffix == ".mcap":
        raise ValueError(f"{src} is a rosbag2 directory: recover it into a directory, not {dst.name}")
    bare_out = dst.suffix == ".mcap"
    if bare_out:
        if dst.exists():
            raise FileExistsError(f"{dst} already exists")
    elif dst.exists() and (not dst.is_dir() or any(dst.iterdir())):
        raise FileExistsError(f"{dst} already exists and is not an empty directory")

    if src.is_file():
        sources = [src]
    else:
        try:
            sources = BagReader(src).files
        except BagFormatError:
            # metadata.yaml unreadable or listing missing files: every MCAP file in the directory instead
            sources = sorted(src.glob("*.mcap"), key=natural_key)
        if not sources:
            raise BagFormatError(f"{src} holds no *.mcap file")
    result = RecoverResult(dst)
    writers = []
    for f in sources:
        out = dst if bare_out else dst / (f.name if f.suffix == ".mcap" else f.name + ".mcap")
        try:
            done, w = _recover_file(f, out, compression, chunk_size)
        except BagFormatError as e:
            if len(sources) == 1:
                raise
            result.files.append(FileRecovery(str(f), None, note=str(e)))  # e.g. a 0-byte last split
            continue
        result.files.append(done)
        writers.append(w)
    if not writers:
        raise BagFormatError(f"no readable MCAP file in {src}")
    if not bare_out:
        result.metadata_yaml = _write_metadata_yaml(dst, writers, compression)
    return result


class _MergedTopic:
    """A topic across the recovered files (first file's type/QoS/hash, summed counts) for metadata.yaml."""

    def __init__(self, t: Any) -> None:
        self.name, self.type_name, self.qos, self.type_hash, self.count = t.name, t.type_name, t.qos, t.type_hash, 0


def _write_metadata_yaml(dst: Path, writers: list[Any], compression: str | None) -> Path:
    topics: dict[str, _MergedTopic] = {}
    files = []
    for w in writers:
        for t in w.topics.values():
            topics.setdefault(t.name, _MergedTopic(t)).count += t.count
        files += w.files
    meta = rosbag2_metadata(topics.values(), files, None if compression == "auto" else compression)
    if compression == "auto":
        comps = {w.compression or "none" for w in writers}
        meta["rosbag2_bagfile_information"]["custom_data"]["chunk_compression"] = ",".join(sorted(comps))
    path = dst / "metadata.yaml"
    try:
        path.write_text(rosbag2_yaml(meta))
    except OSError as e:
        raise BagWriteError(e.errno, f"cannot write {path}: {e.strerror or e}") from e
    return path
