"""Recovery: what survives of a killed, disk-full or damaged recording, as a complete file.

:func:`recover_recording` copies every message of every intact chunk (found through the chunk
index, or by a scan where the summary is missing or damaged:
:class:`~cdpr_dynamics.recording.reader.McapFile`) into a new, indexed file with summary and
footer; ``cdpr_record --recover IN OUT`` calls it.
"""
from __future__ import annotations

import os
from pathlib import Path

from cdpr_dynamics.recording.base import mcap_writer, RecordingError, temporary_file
from cdpr_dynamics.recording.reader import McapFile, Salvage


def recover_recording(source, destination, *, force: bool = False,
                      salvage: Salvage | None = None) -> int:
    """Rewrite the intact chunks of a recording as a complete, indexed file.

    Returns the number of messages kept; ``salvage`` (a :class:`Salvage`) gets the damage
    met and the chunks lost. The source is only read; the destination appears only once
    complete (written under a temporary name in its folder, then renamed), is never the
    source, and an existing one is kept unless ``force``.
    """
    destination = Path(destination)
    salvage = Salvage() if salvage is None else salvage
    if destination.exists() and Path(source).exists() and destination.samefile(source):
        raise RecordingError(f'{destination} is the recording to recover: give another name')
    if destination.exists() and not force:
        raise RecordingError(f'{destination} exists; not overwriting it')
    mcap = McapFile(source)
    try:
        fd, temp = temporary_file(destination)
    except RecordingError:
        mcap.close()
        raise
    try:
        with mcap, os.fdopen(fd, 'wb') as out:
            salvage.damage.extend(mcap.layout.damage)
            writer = mcap_writer(out, library=mcap.header.library, profile=mcap.header.profile)
            schema_ids, channel_ids = {}, {}

            def channel_id(source_id: int) -> int | None:
                if source_id not in channel_ids and source_id in mcap.channels:
                    channel = mcap.channels[source_id]
                    schema = mcap.schemas.get(channel.schema_id)
                    if schema is not None and schema.id not in schema_ids:
                        schema_ids[schema.id] = writer.register_schema(
                            schema.name, schema.encoding, schema.data)
                    channel_ids[source_id] = writer.register_channel(
                        channel.topic, channel.message_encoding,
                        schema_ids.get(channel.schema_id, 0), dict(channel.metadata))
                return channel_ids.get(source_id)

            kept = 0
            for batch in mcap.batches(None, salvage):
                for log_time, publish_time, source_id, data in batch:
                    target = channel_id(source_id)
                    writer.add_message(target, log_time, data, publish_time)
                    kept += 1
            for name, values in mcap.layout.metadata.items():
                writer.add_metadata(name, dict(values))
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
