"""Reading a recording's 3D scene back with the MCAP reader and the protobuf decoder the
MCAP project ships (``mcap-protobuf-support``), as any MCAP tool would."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from foxglove.messages import SceneUpdate
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from swarm.observe.recording import locate
from swarm.observe.scene import SCENE_TOPIC


def read_scenes(recording: Path) -> list[tuple[int, str, str, Any]]:
    """(log_time ns, schema name, channel encoding, decoded SceneUpdate) of every scene."""
    with locate(recording).open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        return [(message.log_time, schema.name, channel.message_encoding, decoded)
                for schema, channel, message, decoded
                in reader.iter_decoded_messages(topics=[SCENE_TOPIC])]


def decode_scene_bytes(data: bytes) -> Any:
    """A SceneUpdate's protobuf bytes, decoded with the schema Foxglove's SDK gives."""
    schema = SceneUpdate.get_schema()
    decoder = DecoderFactory().decoder_for(
        schema.encoding, Schema(id=1, name=schema.name, encoding=schema.encoding,
                                data=schema.data))
    assert decoder is not None
    return decoder(data)


def decode_scene(update: SceneUpdate) -> Any:
    """One SceneUpdate as a reader of its protobuf bytes sees it."""
    return decode_scene_bytes(update.encode())
