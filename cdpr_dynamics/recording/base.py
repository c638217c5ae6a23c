"""What every recording module shares: errors, records read back, type names, the MCAP writer.

Files are rosbag2-compatible (doc/tools/cdpr_record.md): profile ``ros2``, ``ros2msg`` schemas
built from
the installed ``.msg`` files, ``cdr`` channels with rosbag2's channel metadata, indexed chunks.
:func:`mcap_writer` makes the ``mcap`` writer with those settings for the recorder
(:mod:`~cdpr_dynamics.recording.recorder`) and the file writer
(:mod:`~cdpr_dynamics.recording.writer`) alike.
"""
from __future__ import annotations

import importlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, NamedTuple

from mcap.reader import SeekingReader
from mcap.writer import CompressionType, IndexType, Writer

from msg_adapters import mcap_schema

try:
    from importlib.metadata import version as _dist_version
    VERSION = _dist_version('cdpr_dynamics')
except Exception:  # noqa: BLE001 - not installed: a checkout on the path
    VERSION = '0.1.0'

LIBRARY = f'cdpr_dynamics {VERSION} (mcap-python)'
DEFAULT_CHUNK_SIZE = 768 * 1024  # the MCAP C++ writer's default, used by rosbag2
DEFAULT_CHUNK_INTERVAL_S = 1.0
COMPRESSIONS = {'none': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                'lz4': CompressionType.LZ4}


class RecordingError(RuntimeError):
    """A recording that cannot be written or read as asked; the message is one line."""


class UndecodableMessage(RecordingError):
    """One message of a recording that does not decode (the rest of the file may well)."""


class RecordedMessage(NamedTuple):
    """One message read back: topic, type name, receive time (ns) and the message."""

    topic: str
    type: str
    log_time_ns: int
    message: Any


class RawRecordedMessage(NamedTuple):
    """One message read back with ``raw=True``: also its send time and its CDR bytes."""

    topic: str
    type: str
    log_time_ns: int
    message: Any
    publish_time_ns: int
    data: bytes


@dataclass
class TopicInfo:
    """A channel of a recording."""

    type: str
    message_count: int
    offered_qos_profiles: str = ''
    type_hash: str = ''


@dataclass
class RecordingInfo:
    """What :func:`recording_info` finds in a file."""

    path: Path
    complete: bool          # footer, summary and chunk index present
    profile: str
    library: str
    message_count: int
    start_ns: int
    end_ns: int
    chunk_count: int
    topics: dict = field(default_factory=dict)   # name -> TopicInfo
    schema_encodings: dict = field(default_factory=dict)  # type -> encoding
    metadata: dict = field(default_factory=dict)  # metadata record name -> dict
    damage: list = field(default_factory=list)    # what a scan found lost, one line each


@dataclass
class RecordingSummary:
    """What a :class:`Recorder` wrote."""

    path: Path
    message_count: int
    bytes: int
    chunk_count: int
    topics: dict            # resolved name -> messages written (0: never seen)
    start_ns: int
    end_ns: int
    complete: bool = True   # summary and footer written (False: cut at the last whole chunk)
    error: str | None = None  # why writing stopped early (a full disk), one line
    warnings: tuple = ()      # one line each: topics whose messages the file may lack


# ----------------------------------------------------------------------------- types


def type_name_of(msg_class) -> str:
    """``pkg/msg/Type`` of a generated rclpy message class (``pkg/srv/Srv_Event`` too)."""
    package, namespace = msg_class.__module__.split('.')[:2]
    return f'{package}/{namespace}/{msg_class.__name__}'


def message_class(type_name: str):
    """The rclpy class of a type name; raises :class:`RecordingError` if it is not installed."""
    try:
        package, namespace, name = mcap_schema.split_type_name(type_name)
    except mcap_schema.SchemaError as err:
        raise RecordingError(str(err)) from None
    try:
        module = importlib.import_module(f'{package}.{namespace}')
        if namespace == 'srv':
            for suffix, attr in (('_Event', 'Event'), ('_Request', 'Request'),
                                 ('_Response', 'Response')):
                if name.endswith(suffix):
                    return getattr(getattr(module, name[:-len(suffix)]), attr)
        return getattr(module, name)
    except (ImportError, AttributeError):
        raise RecordingError(f'message type {type_name} is not installed') from None


def normalise_topics(topics) -> dict:
    """Topic name -> type name (or None) from names, a mapping to type names or classes."""
    if isinstance(topics, str):
        topics = [topics]
    if isinstance(topics, Mapping):
        items = topics.items()
    else:
        items = ((name, None) for name in topics)
    out = {}
    for name, typ in items:
        if typ is not None and not isinstance(typ, str):
            typ = type_name_of(typ)
        out[name] = typ
    return out


def reason(err: Exception) -> str:
    """``Type: first line`` of an exception, for one-line messages."""
    text = str(err).strip().splitlines()
    return f'{type(err).__name__}: {text[0]}' if text else type(err).__name__


def compression_type(compression: str) -> CompressionType:
    """The ``mcap`` compression of ``'none'``, ``'zstd'`` or ``'lz4'``."""
    if compression not in COMPRESSIONS:
        raise RecordingError(f'unknown compression {compression!r} (none, zstd, lz4)')
    return COMPRESSIONS[compression]


def mcap_writer(stream, chunk_size: int = DEFAULT_CHUNK_SIZE, compression: str = 'none',
                library: str | None = None, profile: str = mcap_schema.PROFILE) -> Writer:
    """A started ``mcap`` writer on ``stream``: the header (profile ``ros2``), indexed chunks
    of about ``chunk_size`` bytes, a summary with statistics, repeated schemas and channels,
    CRCs."""
    writer = Writer(
        stream, chunk_size=int(chunk_size), compression=compression_type(compression),
        index_types=IndexType.ALL, repeat_channels=True, repeat_schemas=True,
        use_chunking=True, use_statistics=True, use_summary_offsets=True, enable_crcs=True)
    writer.start(profile=profile, library=library or LIBRARY)
    return writer


def temporary_file(destination: Path) -> tuple[int, Path]:
    """A new hidden file ``.NAME.partial-XXXX`` beside ``destination`` (fd, path), with the
    permissions a plain new file gets (mkstemp's 0600 would outlive the rename)."""
    try:
        fd, temp = tempfile.mkstemp(prefix=f'.{destination.name}.partial-',
                                    dir=destination.parent)
    except OSError as err:
        raise RecordingError(f'cannot write {destination}: {err.strerror or err}') from None
    try:
        mask = os.umask(0)
        os.umask(mask)
        os.fchmod(fd, 0o666 & ~mask)
    except BaseException:   # Ctrl-C right now: nobody else knows the name to remove it
        os.close(fd)
        os.unlink(temp)
        raise
    return fd, Path(temp)


def count_chunks(path: Path) -> int:
    """Chunks of a complete file by its statistics (0 where unreadable: only a figure)."""
    try:
        with open(path, 'rb') as stream:
            summary = SeekingReader(stream).get_summary()
        return summary.statistics.chunk_count if summary and summary.statistics else 0
    except Exception:  # noqa: BLE001 - only a figure for the summary
        return 0
