"""The radio on the wire (docs/network.md): a frame's radio links, the truth's link matrix,
telemetry's neighbours heard and reach, and a range graph's round 0 with its reach stamps,
each checked against this swarm's N with one reason when it does not fit."""

from __future__ import annotations

import dataclasses

import msgspec
import numpy as np
import pytest

from swarm.core.consensus_message import message_size
from swarm.messages.rules import WireError
from swarm.messages.wire import (
    WIRE_VERSION,
    CameraFrameWire,
    F64Array,
    TelemetryWire,
    TruthWire,
    WireCodec,
    consensus_to_wire,
    telemetry_from_diagnostics,
)
from tests.helpers.wire_samples import (
    CODEC,
    MESSAGES,
    NS,
    M,
    N,
    consensus_message,
    real_agent_outputs,
)


def rule_of(decode, payload: bytes) -> str:
    with pytest.raises(WireError) as info:
        decode(payload)
    return info.value.rule


def raw_payload(kind: str, message) -> bytes:
    """``message``'s bytes as msgspec writes them, unchecked (the codec's encode checks)."""
    return msgspec.msgpack.encode(
        (kind, WIRE_VERSION, *[getattr(message, f) for f in type(message).__struct_fields__[1:]]))


def test_a_frame_says_whom_its_drone_hears_never_itself() -> None:
    frame = CODEC.decode_camera(CODEC.encode(MESSAGES["camera_radio"]))
    assert frame.radio_neighbours() == (0, 2, 3)
    own = CameraFrameWire.build(1, 9, 0.18, 0, [], radio_links=[0, 1, 0, 1, 0, 0])
    assert own.radio_neighbours() == (3,)  # its own byte is never a neighbour
    assert MESSAGES["camera_plain"].radio_neighbours() is None


@pytest.mark.parametrize(("links", "reason"), [(b"\x01" * (N - 1), "shape"),
                                               (b"\x01" * (N + 1), "shape"),
                                               (b"\x00\x02" + b"\x00" * (N - 2), "range")])
def test_a_bad_radio_mask_is_refused_with_its_reason(links: bytes, reason: str) -> None:
    bad = msgspec.structs.replace(MESSAGES["camera_radio"], radio_links=links)
    assert rule_of(CODEC.decode_camera, raw_payload("camera", bad)) == reason


def test_truth_carries_the_link_matrix_and_refuses_another_shape() -> None:
    truth = CODEC.decode_truth(CODEC.encode(MESSAGES["truth_radio"]))
    links = truth.radio_link_matrix()
    assert links is not None and links.shape == (N, N) and links[0, 1] and not links[0, 2]
    assert MESSAGES["truth"].radio_link_matrix() is None
    bad = msgspec.structs.replace(MESSAGES["truth_radio"],
                                  radio_links=F64Array.from_array(np.zeros((N - 1, N - 1))))
    with pytest.raises(WireError, match="radio_links") as info:
        CODEC.decode_truth(raw_payload("truth", bad))
    assert info.value.rule == "shape"


def test_telemetry_carries_the_neighbours_heard_reach_and_keep_figures() -> None:
    _, diag = real_agent_outputs()
    diag = dataclasses.replace(diag, neighbours_heard=(1, 5), reached=4, keep_margin_m=0.75,
                               link_conflict=True)
    tel = CODEC.decode_telemetry(CODEC.encode_telemetry(diag, [0.0, 0.0, 3.0]))
    assert tel.neighbours_heard == bytes([0, 1, 0, 0, 0, 1])
    again = tel.to_diagnostics()
    assert (again.neighbours_heard, again.reached, again.keep_margin_m, again.link_conflict) == (
        (1, 5), 4, 0.75, True)
    plain = telemetry_from_diagnostics(diag, [0.0, 0.0, 3.0])  # no N given: no mask
    assert plain.neighbours_heard is None and plain.to_diagnostics().neighbours_heard == ()
    no_keep = CODEC.decode_telemetry(CODEC.encode_telemetry(
        dataclasses.replace(diag, keep_margin_m=np.inf), [0.0, 0.0, 3.0]))
    assert no_keep.keep_margin_m is None and no_keep.to_diagnostics().keep_margin_m == np.inf
    assert isinstance(tel, TelemetryWire)


def _round0_with_stamps(stamps: np.ndarray):
    message = consensus_message()
    data = np.concatenate((message.data, stamps))
    return consensus_to_wire(dataclasses.replace(message, data=data))


def test_a_range_graph_round_0_carries_n_reach_stamps_checked_as_the_rest() -> None:
    ranged = WireCodec(N, M, NS, reach_stamps=True)
    good = _round0_with_stamps(np.arange(N, dtype=float))
    decoded = ranged.decode_consensus(ranged.encode(good))
    assert decoded.data.shape[0] == message_size(M, NS, True) + N
    np.testing.assert_array_equal(decoded.data[-N:], np.arange(N, dtype=float))
    assert decoded.has_states and decoded.gramian is not None
    # Without the stamps, with too few, or a NaN stamp: refused, each with its reason.
    plain = consensus_to_wire(consensus_message())
    assert rule_of(ranged.decode_consensus, CODEC.encode(plain)) == "shape"
    short = _round0_with_stamps(np.zeros(N - 1))
    assert rule_of(ranged.decode_consensus, raw_payload("consensus", short)) == "shape"
    stamps = np.zeros(N)
    stamps[2] = np.nan
    nan = _round0_with_stamps(stamps)
    with pytest.raises(WireError, match="reach_stamps") as info:
        ranged.decode_consensus(raw_payload("consensus", nan))
    assert info.value.rule == "finite"
    # A fixed graph's codec refuses the stamps; later rounds carry none either way.
    assert rule_of(CODEC.decode_consensus, ranged.encode(good)) == "shape"
    later = consensus_to_wire(consensus_message(round_=2))
    assert ranged.decode_consensus(ranged.encode(later)).data.shape[0] == message_size(
        M, NS, False)


def test_truth_without_links_is_the_fixed_graph() -> None:
    truth = TruthWire.build(0, 0.0, np.zeros((N, 3)), np.zeros((M, 3)), np.zeros((M, 3)))
    assert truth.radio_links is None
