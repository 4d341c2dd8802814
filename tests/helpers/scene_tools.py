"""Reading a recording's 3D scene back with the MCAP reader and the protobuf decoder the
MCAP project ships (``mcap-protobuf-support``), as any MCAP tool would."""

from __future__ import annotations

from typing import Any

from foxglove.messages import Log, SceneUpdate
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from tools.render_scene import read_scenes  # noqa: F401 (the tests read scenes as it does)


def _decode(message_type: Any, data: bytes) -> Any:
    schema = message_type.get_schema()
    decoder = DecoderFactory().decoder_for(
        schema.encoding, Schema(id=1, name=schema.name, encoding=schema.encoding,
                                data=schema.data))
    assert decoder is not None
    return decoder(data)


def decode_scene_bytes(data: bytes) -> Any:
    """A SceneUpdate's protobuf bytes, decoded with the schema Foxglove's SDK gives."""
    return _decode(SceneUpdate, data)


def decode_log(line: Log) -> Any:
    """One foxglove.Log as a reader of its protobuf bytes sees it."""
    return _decode(Log, line.encode())


def decode_scene(update: SceneUpdate) -> Any:
    """One SceneUpdate as a reader of its protobuf bytes sees it."""
    return decode_scene_bytes(update.encode())
