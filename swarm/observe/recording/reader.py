"""Reading a recording back: ``read_recording`` (the run record, metadata and what the drones
reported) and ``iter_messages`` (the messages themselves, as wire structs).

Records are read sequentially, so a file cut short by a crash (no footer, a partial last
record) reads up to the cut, and says so (``truncated``); a file still being written reads
up to its last flush. Every message is checked as a received payload would be.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Final, TypeVar

import msgspec
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel, DataEnd, Message, Metadata
from mcap.stream_reader import StreamReader

from swarm.messages.rules import WireError
from swarm.messages.wire import TelemetryCounters, TelemetryWire, TruthWire, WireCodec
from swarm.observe.collector import TelemetryCollector
from swarm.observe.recording.schema import (
    KIND_NAMED,
    KINDS,
    METADATA_NAME,
    RECORDING_FILE,
    AutopilotState,
    Recordable,
    RecordingFileError,
    RecordingMetadata,
    parse_topic,
)
from swarm.runs.record import RunRecord
from swarm.scenario.config import ScenarioConfig

_R = TypeVar("_R", bound=Recordable)

# msgspec's JSON is ~10x faster than the json module, with the same exact shortest-repr floats.
_JSON_DECODER: Final = msgspec.json.Decoder()


class _WholeReads:
    """File reads that never return a short piece: a record cut by a crash raises EndOfFile
    (the end of the usable data) instead of becoming a garbled record."""

    def __init__(self, handle: IO[bytes]) -> None:
        self._handle = handle

    def read(self, size: int) -> bytes:
        data = self._handle.read(size)
        if len(data) < size:
            raise EndOfFile()
        return data


@dataclass(frozen=True)
class RecordedMessage:
    """One message of a recording, converted back to its wire struct."""

    topic: str
    kind: str  # "telemetry", "beacon", "camera", "truth" or "autopilot"
    drone: int | None  # from the topic; None for world/truth
    log_time_ns: int  # sim time of its step
    publish_time_ns: int  # wall time of receipt
    message: Recordable


class _RecordStream:
    """Sequential MCAP records of a file, stopping cleanly where a crash cut it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.truncated = True  # until the end of the data section is seen

    def __iter__(self) -> Iterator[Metadata | Channel | Message]:
        with self.path.open("rb") as handle:
            # mcap annotates the input as IO[bytes]; the reader only calls read(n) on it.
            reader = StreamReader(_WholeReads(handle),  # type: ignore[arg-type]
                                  record_size_limit=1 << 30)
            try:
                for record in reader.records:
                    if isinstance(record, DataEnd):
                        self.truncated = False
                        return  # the summary after it repeats what was already read
                    if isinstance(record, Metadata | Channel | Message):
                        yield record
            except EndOfFile:
                if handle.tell() < 8:
                    raise RecordingFileError(f"{self.path}: empty or cut before the MCAP header "
                                         "(is the run still starting?)") from None
            except InvalidMagic:
                raise RecordingFileError(f"{self.path}: not an MCAP file") from None
            except (McapError, ValueError, KeyError) as err:
                raise RecordingFileError(f"{self.path}: corrupt MCAP data: {err}") from None


def locate(path: Path) -> Path:
    """The .mcap file of a recording given as its directory or as the file itself."""
    path = Path(path)
    if path.is_dir():
        path = path / RECORDING_FILE
        if not path.is_file():
            raise RecordingFileError(f"{path.parent}: no {RECORDING_FILE} in this directory "
                                     "(not a recording made with --record?)")
        return path
    if not path.exists():
        raise RecordingFileError(f"{path}: no such file or directory")
    return path


def _decode(kind: str, data: bytes, codec: WireCodec | None, where: str) -> Recordable:
    """JSON → the wire struct, checked like a received payload when a codec is given."""
    try:
        message = KIND_NAMED[kind].from_json(_JSON_DECODER.decode(data))
        if codec is not None and not isinstance(message, AutopilotState):
            codec.validate(message)
        return message
    except WireError as err:
        raise RecordingFileError(f"{where}: invalid {kind} message: {err.reason}") from None
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError, KeyError,
            TypeError) as err:
        raise RecordingFileError(f"{where}: malformed {kind} message: "
                                 f"{type(err).__name__}: {err}") from None


def _decode_as(cls: type[_R], kind: str, data: bytes, codec: WireCodec | None,
               where: str) -> _R:
    """``_decode`` of a channel of ``kind``, whose messages are ``cls`` (``KIND_NAMED``)."""
    message = _decode(kind, data, codec, where)
    if not isinstance(message, cls):
        raise RecordingFileError(f"{where}: a {kind} channel holds a {type(message).__name__}")
    return message


def _codec(config: ScenarioConfig) -> WireCodec:
    return config.wire_codec()


def iter_messages(path: Path, kinds: tuple[str, ...] = KINDS) -> Iterator[RecordedMessage]:
    """Every message of the given kinds in file order (a cut-short file: up to the cut)."""
    file = locate(path)
    channels: dict[int, tuple[str, str, int | None]] = {}
    codec: WireCodec | None = None
    for record in _RecordStream(file):
        if isinstance(record, Metadata) and record.name == METADATA_NAME:
            codec = _codec(RecordingMetadata.from_mcap(record.metadata, str(file)).config)
        elif isinstance(record, Channel):
            parsed = parse_topic(record.topic)
            if parsed is not None:
                channels[record.id] = (record.topic, *parsed)
        elif isinstance(record, Message) and record.channel_id in channels:
            name, kind, drone = channels[record.channel_id]
            if kind in kinds:
                yield RecordedMessage(name, kind, drone, record.log_time, record.publish_time,
                                      _decode(kind, record.data, codec, f"{file}: {name}"))


@dataclass(frozen=True)
class Recording:
    """A recording read back: metadata, the run record and what the drones reported."""

    path: Path  # the .mcap file
    metadata: RecordingMetadata
    record: RunRecord  # up to the newest truth step; NaN where a message is missing
    drone_counters: dict[int, TelemetryCounters]  # newest running totals per drone
    message_counts: dict[str, int]  # per topic
    truncated: bool  # no clean end: the writer was killed, or is still writing
    missing_samples: int  # (step, positions or velocities) samples with no message
    last_publish_time_ns: int  # wall time of receipt of the newest message (0: none)
    sim_time_s: float  # sim time of the newest message (0 without messages)

    @property
    def config(self) -> ScenarioConfig:
        return self.metadata.config


def read_recording(path: Path, *, fill_gaps: bool = False) -> Recording:
    """Read ``DIR`` (or ``DIR/run.mcap``), also while it is written or after a crash.

    The record is built exactly as the launcher builds its own (``TelemetryCollector``);
    ``fill_gaps`` fills missing steps as the launcher's summary does instead of leaving NaN.
    Raises RecordingFileError (one line) for a missing path, a non-MCAP file, a file without
    Vigil metadata or a malformed message.
    """
    file = locate(path)
    stream = _RecordStream(file)
    metadata: RecordingMetadata | None = None
    collector: TelemetryCollector | None = None
    codec: WireCodec | None = None
    channels: dict[int, tuple[str, str]] = {}
    counts: dict[str, int] = {}
    last_publish, last_log = 0, 0
    for record in stream:
        if isinstance(record, Metadata) and record.name == METADATA_NAME:
            metadata = RecordingMetadata.from_mcap(record.metadata, str(file))
            collector = TelemetryCollector(metadata.config)
            codec = _codec(metadata.config)
        elif isinstance(record, Channel):
            parsed = parse_topic(record.topic)
            if parsed is not None:
                channels[record.id] = (record.topic, parsed[0])
                counts.setdefault(record.topic, 0)
        elif isinstance(record, Message) and record.channel_id in channels:
            name, kind = channels[record.channel_id]
            if collector is None:
                break  # reported below: messages before any Vigil metadata
            counts[name] += 1
            last_publish = max(last_publish, record.publish_time)
            last_log = max(last_log, record.log_time)
            if kind == "telemetry":
                collector.on_telemetry(name, _decode_as(TelemetryWire, kind, record.data, codec,
                                                        f"{file}: {name}"))
            elif kind == "truth":
                collector.on_truth(name, _decode_as(TruthWire, kind, record.data, codec,
                                                    f"{file}: {name}"),
                                   received_s=record.publish_time / 1e9)
    if metadata is None or collector is None:
        raise RecordingFileError(f"{file}: no Vigil metadata (an MCAP file, but not a "
                                 "recording made by launch-swarm --record)")
    wall_s = max(last_publish - metadata.start_time_ns, 0) / 1e9 if last_publish else 0.0
    run_record = collector.record(metadata.seed, wall_s, fill=fill_gaps)
    return Recording(
        path=file, metadata=metadata, record=run_record,
        drone_counters=collector.drone_counters(),
        message_counts=counts, truncated=stream.truncated,
        missing_samples=collector.missing_samples, last_publish_time_ns=last_publish,
        sim_time_s=last_log / 1e9)
