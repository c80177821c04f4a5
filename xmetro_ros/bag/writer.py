"""Write MCAP bags exactly as ``ros2 bag record -s mcap`` does, with the ``mcap`` library.

Per file, as rosbag2_storage_mcap writes it: header profile ``ros2``; one ``ros2msg`` schema per type (text with
dependencies, see :mod:`.schema`); channels with encoding ``cdr`` and metadata ``offered_qos_profiles`` (the
publishers' profiles, YAML, see :mod:`.qos`) + ``topic_type_hash`` (RIHS01); messages chunked (optionally zstd) and
indexed; a ``rosbag2`` metadata record ``{serialized_metadata: <BagMetadata YAML>}`` when the file is opened and
again when it is closed (``MCAPStorage::update_metadata``: the bare BagMetadata mapping, version 9, ``ros_distro``
inside it); summary with statistics. Output layouts:

- ``path`` ending in ``.mcap``: one bare MCAP file (no splitting).
- any other ``path``: a rosbag2 directory ``path/`` holding ``<name>_0.mcap``, ``<name>_1.mcap``, ... and
  ``metadata.yaml`` (version 9), split by size and/or duration.

Crash safety: the file is written unbuffered and every finished chunk goes to the OS at once, so a writer killed
with SIGKILL leaves every completed chunk readable (:class:`~.reader.BagReader` recovers them). A write error
(e.g. disk full, ENOSPC) raises :class:`BagWriteError`; everything written before stays readable.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml
from mcap.writer import CompressionType, Writer

from .codec import serialize
from .qos import offered_qos_list, offered_qos_yaml
from .schema import full_type_name, schema_text, type_hash

__all__ = ["ROS_DISTRO", "BagWriteError", "BagWriter", "rosbag2_metadata", "rosbag2_yaml"]

ROS_DISTRO = "kilted"
LIBRARY = "xmetro_ros bag writer (mcap python)"
METADATA_VERSION = 9


class BagWriteError(OSError):
    """Writing the bag failed (disk full, file system error, bad arguments to a closed writer...)."""


class _SafeFile:
    """Unbuffered binary file: every write reaches the OS in full (loops on short writes) or raises.

    Deliberately not an ``io.RawIOBase``: mcap's Writer would wrap that in a BufferedWriter, and a killed recorder
    would then lose completed chunks still sitting in the buffer.
    """

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self._pos = 0
        self.closed = False

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):
            done += os.write(self._fd, view[done:])
        self._pos += done
        return done

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            os.close(self._fd)


@dataclass
class _Topic:
    name: str
    type_name: str
    qos: list[dict[str, Any]]  # offered profiles, rosbag2 v9 mappings
    type_hash: str
    schema_data: bytes
    schema_encoding: str = "ros2msg"
    count: int = 0

    @property
    def qos_yaml(self) -> str:
        """The channel metadata string (``offered_qos_profiles``)."""
        return offered_qos_yaml(self.qos)


@dataclass
class _FileStats:
    path: str
    start_ns: int | None = None
    end_ns: int | None = None
    count: int = 0

    def add(self, t: int) -> None:
        self.start_ns = t if self.start_ns is None else min(self.start_ns, t)
        self.end_ns = t if self.end_ns is None else max(self.end_ns, t)
        self.count += 1


@dataclass
class _Open:
    stream: IO[bytes]
    writer: Writer
    stats: _FileStats
    schema_ids: dict[str, int] = field(default_factory=dict)
    channel_ids: dict[str, int] = field(default_factory=dict)
    sequence: Counter = field(default_factory=Counter)


class _YamlCppStyle(yaml.SafeDumper):
    """PyYAML emitting the way yaml-cpp (rosbag2) does: block sequences indented under their key, ``""`` for empty
    strings. Only the look differs from PyYAML's default; the YAML is the same."""

    def increase_indent(self, flow: bool = False, indentless: bool = False) -> Any:
        return super().increase_indent(flow, False)

    def ignore_aliases(self, data: Any) -> bool:
        return True  # a mapping used twice is written twice (yaml-cpp writes no anchors)


_YamlCppStyle.add_representer(
    str, lambda d, v: d.represent_scalar("tag:yaml.org,2002:str", v, style='"' if v == "" else None))


def rosbag2_yaml(data: Any) -> str:
    """``data`` as YAML in rosbag2's (yaml-cpp's) block style, keys in the given order."""
    return yaml.dump(data, Dumper=_YamlCppStyle, sort_keys=False, default_flow_style=False, allow_unicode=True)


def rosbag2_metadata(topics: Iterable[Any], files: list[Any], compression: str | None) -> dict[str, Any]:
    """``{rosbag2_bagfile_information: BagMetadata}`` (metadata.yaml, version 9) for the given topics and files.

    Keys and their order as rosbag2_storage's ``convert<BagMetadata>::encode`` (yaml.hpp) writes them; topics'
    ``offered_qos_profiles`` as a sequence (version 9).
    """
    files = list(files)
    starts = [f.start_ns for f in files if f.start_ns is not None]
    ends = [f.end_ns for f in files if f.end_ns is not None]
    start = min(starts) if starts else 0
    duration = (max(ends) - start) if ends else 0
    return {
        "rosbag2_bagfile_information": {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": int(duration)},
            "starting_time": {"nanoseconds_since_epoch": int(start)},
            "message_count": int(sum(f.count for f in files)),
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": t.name,
                        "type": t.type_name,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": list(t.qos),
                        "type_description_hash": t.type_hash,
                    },
                    "message_count": int(t.count),
                }
                for t in topics
            ],
            # rosbag2 compresses whole files or messages; we compress MCAP chunks (the storage plugin's own
            # zstd), which readers handle transparently, so the bag-level compression stays empty.
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [Path(f.path).name for f in files],
            "files": [
                {
                    "path": Path(f.path).name,
                    "starting_time": {"nanoseconds_since_epoch": int(f.start_ns or 0)},
                    "duration": {"nanoseconds": int((f.end_ns or 0) - (f.start_ns or 0))},
                    "message_count": int(f.count),
                }
                for f in files
            ],
            "custom_data": {"writer": LIBRARY, "chunk_compression": compression or "none"},
            "ros_distro": ROS_DISTRO,
        }
    }


class BagWriter:
    """Write ROS 2 messages to an MCAP bag in rosbag2's format.

    Args:
        path: ``*.mcap`` → one bare file; otherwise a rosbag2 directory (created; must not exist or be empty).
        compression: None (default) or ``"zstd"`` (per MCAP chunk).
        chunk_size: bytes of uncompressed messages per chunk (a chunk is closed as soon as it exceeds this).
        split_size: start a new file once the current one holds at least this many bytes (directory only).
        split_duration: start a new file once a message is this many seconds (log time) after the file's first
            message (directory only).
        opener: for tests: ``opener(path) -> binary file object`` replacing the unbuffered file.

    Raises:
        ValueError: bad arguments; FileExistsError: output exists; BagWriteError: an I/O error while writing.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        compression: str | None = None,
        chunk_size: int = 1024 * 1024,
        split_size: int | None = None,
        split_duration: float | None = None,
        opener: Callable[[Path], IO[bytes]] | None = None,
    ) -> None:
        self.path = Path(path)
        if compression not in (None, "", "none", "zstd"):
            raise ValueError(f"compression must be None or 'zstd', got {compression!r}")
        self.compression = "zstd" if compression == "zstd" else None
        if chunk_size <= 0:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        self.chunk_size = int(chunk_size)
        self.bare = self.path.suffix == ".mcap"
        if (split_size or split_duration) and self.bare:
            raise ValueError("splitting needs a bag directory as output (a path not ending in .mcap)")
        if (split_size is not None and split_size <= 0) or (split_duration is not None and split_duration <= 0):
            raise ValueError("split_size and split_duration must be positive")
        self.split_size = split_size
        self.split_duration_ns = None if split_duration is None else int(split_duration * 1e9)
        self._opener = opener or _SafeFile
        if self.bare:
            if self.path.exists():
                raise FileExistsError(f"bag file {self.path} already exists")
            self.path.parent.mkdir(parents=True, exist_ok=True)
        else:
            if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
                raise FileExistsError(f"bag directory {self.path} already exists and is not empty")
            self.path.mkdir(parents=True, exist_ok=True)
        self.topics: dict[str, _Topic] = {}
        self.files: list[_FileStats] = []
        self._cur: _Open | None = None
        self._closed = False
        self._failed: BaseException | None = None
        self._open_next()

    # -- files ---------------------------------------------------------------------------------------------
    def _file_path(self, index: int) -> Path:
        return self.path if self.bare else self.path / f"{self.path.name}_{index}.mcap"

    def _guard(self, what: str, fn: Callable[[], Any]) -> Any:
        try:
            return fn()
        except OSError as e:
            self._failed = e
            written = sum(f.count for f in self.files)
            raise BagWriteError(
                e.errno, f"bag write failed while {what} in {self.files[-1].path if self.files else self.path}: "
                f"{e.strerror or e}; the {written} messages written in completed chunks before stay readable"
            ) from e

    def _open_next(self) -> None:
        p = self._file_path(len(self.files))
        stream = self._guard("creating the file", lambda: self._opener(p))
        w = Writer(
            stream,
            chunk_size=self.chunk_size,
            compression=CompressionType.ZSTD if self.compression else CompressionType.NONE,
        )
        self._cur = _Open(stream, w, _FileStats(str(p)))
        self.files.append(self._cur.stats)
        self._guard("writing the header", lambda: w.start(profile="ros2", library=LIBRARY))
        self._write_rosbag2_record(self._cur)  # rosbag2 writes one at open too: a killed file still says what it is
        for t in self.topics.values():
            self._register(t)

    def _register(self, t: _Topic) -> None:
        cur = self._cur
        assert cur is not None
        if t.type_name not in cur.schema_ids:
            cur.schema_ids[t.type_name] = self._guard("writing a schema", lambda: cur.writer.register_schema(
                t.type_name, t.schema_encoding, t.schema_data))
        cur.channel_ids[t.name] = self._guard("writing a channel", lambda: cur.writer.register_channel(
            t.name, "cdr", cur.schema_ids[t.type_name],
            {"offered_qos_profiles": t.qos_yaml, "topic_type_hash": t.type_hash}))

    def _finish_file(self) -> None:
        cur = self._cur
        if cur is None:
            return
        self._cur = None
        try:
            if self._failed is None:
                self._write_rosbag2_record(cur)
                self._guard("writing the summary", cur.writer.finish)
        finally:
            try:
                cur.stream.close()
            except OSError:
                pass

    def _write_rosbag2_record(self, cur: _Open) -> None:
        """The ``rosbag2`` metadata record of file ``cur``: ``serialized_metadata`` = the bare BagMetadata."""
        meta = rosbag2_metadata(self.topics.values(), [cur.stats], self.compression)["rosbag2_bagfile_information"]
        self._guard("writing the metadata record", lambda: cur.writer.add_metadata(
            "rosbag2", {"serialized_metadata": rosbag2_yaml(meta)}))

    # -- public API ----------------------------------------------------------------------------------------
    def add_topic(self, topic: str, type_name: str, qos: Iterable[Any] | str | None = None, *,
                  schema: tuple[str, bytes] | None = None, topic_type_hash: str | None = None) -> None:
        """Declare ``topic`` of ``type_name`` (``pkg/msg/Type``) with its publishers' offered QoS profiles.

        Args:
            qos: the offered profiles: rclpy QoSProfiles, rosbag2 mappings (:mod:`.qos_profiles`) or an
                ``offered_qos_profiles`` string of any rosbag2 version; None = unknown (recorded as ``[]``).
            schema: ``(encoding, data)`` to store instead of the installed ``.msg`` text (copying a bag whose types
                are not installed here); then ``topic_type_hash`` is stored as given ("" when None).

        Raises UnknownTypeError (from :mod:`.schema`) when the type's .msg is not installed and no ``schema`` is
        given; ValueError when the topic exists with another type or ``qos`` is malformed.
        """
        self._check_open()
        type_name = full_type_name(type_name) if schema is None else type_name
        if topic in self.topics:
            if self.topics[topic].type_name != type_name:
                raise ValueError(f"topic {topic} already added with type {self.topics[topic].type_name}")
            return
        profiles = offered_qos_list(qos)
        if schema is None:
            t = _Topic(topic, type_name, profiles, type_hash(type_name), schema_text(type_name).encode())
        else:
            t = _Topic(topic, type_name, profiles, topic_type_hash or "", bytes(schema[1]), schema[0])
        self.topics[topic] = t
        self._register(t)

    def write(self, topic: str, msg: Any, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Write one message (an rclpy message, or its CDR bytes) on an added topic at ``log_time_ns``."""
        self._check_open()
        if topic not in self.topics:
            raise KeyError(f"topic {topic} was not added (call add_topic first)")
        data = msg if isinstance(msg, (bytes, bytearray, memoryview)) else serialize(msg)
        log_time_ns = int(log_time_ns)
        self._maybe_split(len(data), log_time_ns)
        cur = self._cur
        assert cur is not None
        t = self.topics[topic]
        seq = cur.sequence[topic]
        cur.sequence[topic] += 1
        self._guard("writing a message", lambda: cur.writer.add_message(
            cur.channel_ids[topic], log_time_ns, bytes(data),
            int(publish_time_ns if publish_time_ns is not None else log_time_ns), seq))
        cur.stats.add(log_time_ns)
        t.count += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write an MCAP metadata record (string → string) into the current file."""
        self._check_open()
        cur = self._cur
        assert cur is not None
        self._guard("writing a metadata record", lambda: cur.writer.add_metadata(name, dict(data)))

    def add_attachment(self, name: str, data: bytes, media_type: str = "application/octet-stream",
                       log_time_ns: int = 0) -> None:
        """Write an MCAP attachment into the current file."""
        self._check_open()
        cur = self._cur
        assert cur is not None
        self._guard("writing an attachment", lambda: cur.writer.add_attachment(
            int(log_time_ns), int(log_time_ns), name, media_type, bytes(data)))

    def _maybe_split(self, nbytes: int, log_time_ns: int) -> None:
        cur = self._cur
        st = cur.stats if cur else None
        if self.bare or cur is None or st is None or st.count == 0:
            return
        too_big = self.split_size is not None and cur.stream.tell() + nbytes > self.split_size
        too_long = self.split_duration_ns is not None and log_time_ns - (st.start_ns or 0) >= self.split_duration_ns
        if too_big or too_long:
            self._finish_file()
            self._open_next()

    def _check_open(self) -> None:
        if self._closed:
            raise BagWriteError(f"bag {self.path} is closed")
        if self._failed is not None:
            raise BagWriteError(f"bag {self.path} failed earlier: {self._failed}")

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def close(self) -> None:
        """Finish the current file (summary, metadata record) and, for a directory, write metadata.yaml."""
        if self._closed:
            return
        self._closed = True
        self._finish_file()
        if not self.bare:
            meta = rosbag2_metadata(self.topics.values(), self.files, self.compression)
            text = rosbag2_yaml(meta)
            try:
                (self.path / "metadata.yaml").write_text(text)
            except OSError as e:
                raise BagWriteError(e.errno, f"cannot write {self.path / 'metadata.yaml'}: {e.strerror or e}") from e
        if self._failed is not None:
            raise BagWriteError(f"bag {self.path} was closed after a write error: {self._failed}")

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        if exc_type is not None and self._failed is not None:
            # The original error is already propagating; close quietly so the file stays as readable as it is.
            self._closed = True
            if self._cur is not None:
                try:
                    self._cur.stream.close()
                except OSError:
                    pass
            return
        self.close()
