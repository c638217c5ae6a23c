"""Recovery: what survives of a killed or disk-full recording, as a complete file.

:func:`recover_recording` copies every message of every whole chunk (the records a scan of the
file finds before the cut: :func:`~cdpr_dynamics.recording.reader.scan`) into a new, indexed
file with summary and footer; ``cdpr_record --recover IN OUT`` calls it.
"""
from __future__ import annotations

import os
from pathlib import Path

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema

from cdpr_dynamics.recording.base import mcap_writer, RecordingError, temporary_file
from cdpr_dynamics.recording.reader import open_mcap, scan


def recover_recording(source, destination, *, force: bool = False) -> int:
    """Rewrite what survives of an incomplete recording as a complete, indexed file.

    Returns the number of messages kept. The source is only read; the destination appears only
    once complete (written under a temporary name in its folder, then renamed), is never the
    source, and an existing one is kept unless ``force``.
    """
    destination = Path(destination)
    if destination.exists() and Path(source).exists() and destination.samefile(source):
        raise RecordingError(f'{destination} is the recording to recover: give another name')
    if destination.exists() and not force:
        raise RecordingError(f'{destination} exists; not overwriting it')
    source, stream = open_mcap(source)
    try:
        fd, temp = temporary_file(destination)
    except RecordingError:
        stream.close()
        raise
    try:
        with stream, os.fdopen(fd, 'wb') as out:
            try:
                header = SeekingReader(stream).get_header()
            except (McapError, EndOfFile, ValueError) as exc:
                raise RecordingError(f'{source}: no readable MCAP header ({exc})') from None
            writer = mcap_writer(out, library=header.library, profile=header.profile)
            schema_ids, channel_ids = {}, {}
            kept = 0
            stream.seek(0)
            for record in scan(source, stream):
                if isinstance(record, Schema) and record.id not in schema_ids:
                    schema_ids[record.id] = writer.register_schema(
                        record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channel_ids:
                    channel_ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding,
                        schema_ids.get(record.schema_id, 0), dict(record.metadata))
                elif isinstance(record, Message) and record.channel_id in channel_ids:
                    writer.add_message(channel_ids[record.channel_id], record.log_time,
                                       record.data, record.publish_time, record.sequence)
                    kept += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
            writer.finish()
        if force:
            os.replace(temp, destination)
        else:
            os.link(temp, destination)      # fails if the name appeared meanwhile
            os.unlink(temp)
    except FileExistsError:
        os.unlink(temp)
        raise RecordingError(f'{destination} exists; not overwriting it') from None
    except BaseException:
        if os.path.exists(temp):
            os.unlink(temp)
        raise
    return kept
