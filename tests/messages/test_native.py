"""The wire's compiled work on float64 bytes (``swarm.messages.native``, ``_wire.c``) against
its numpy forms, and the columns of a relayed beacon's row as the C module exports them."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.messages import _wire, native, wire
from swarm.messages.native import join_native, native_finite
from swarm.messages.wire import BeaconRelayWire, BeaconWire


@settings(max_examples=300, deadline=None)
@given(values=st.lists(st.one_of(st.floats(), st.sampled_from([0.0, -0.0, 1e308, -1e-320])),
                       max_size=40),
       cuts=st.lists(st.integers(0, 40), max_size=4), shift=st.integers(0, 7))
def test_native_finite_is_isfinite_all(values: list[float], cuts: list[int], shift: int) -> None:
    """``native_finite`` (the wire rules' check of received floats) is
    ``np.isfinite(...).all()`` of the floats in all its parts together, however they are cut
    and wherever in memory they start (unaligned: a memoryview ``shift`` bytes in)."""
    raw = np.array(values, dtype=np.float64).tobytes()
    bounds = sorted({0, len(values), *(min(c, len(values)) for c in cuts)})
    parts = [raw[8 * a:8 * b] for a, b in itertools.pairwise(bounds)]
    shifted = [memoryview(b"x" * shift + part)[shift:] for part in parts]
    expected = bool(np.isfinite(np.array(values, dtype=np.float64)).all())
    assert native_finite(*parts) is expected
    assert native_finite(*shifted) is expected
    assert native_finite() is True


def test_native_finite_names_a_part_that_is_not_floats() -> None:
    with pytest.raises(ValueError, match="part 1 holds 12 bytes"):
        native_finite(b"", b"x" * 12)
    with pytest.raises(TypeError, match="part 0 is not bytes-like"):
        native_finite([1.0])


_SHAPES = st.lists(st.lists(st.integers(0, 4), min_size=0, max_size=3).map(tuple),
                   min_size=0, max_size=12)


@given(_SHAPES, st.data())
def test_join_native_is_the_join_of_the_arrays_bytes(shapes: list[tuple[int, ...]],
                                                    data: st.DataObject) -> None:
    """``join_native`` (the telemetry's packing) is ``b"".join(a.tobytes())`` of native
    float64 arrays of the given shapes, and None as soon as one array is anything else: another
    dtype or byte order, not C-contiguous, another shape, not an array."""
    arrays = [np.asarray(data.draw(st.lists(st.floats(allow_nan=True), min_size=math.prod(s),
                                            max_size=math.prod(s))),
                         dtype=np.float64).reshape(s) for s in shapes]
    expected = b"".join(a.tobytes() for a in arrays)
    assert join_native(tuple(arrays), tuple(shapes)) == expected
    if not arrays:
        return
    k = data.draw(st.integers(0, len(arrays) - 1))
    a = arrays[k]
    with np.errstate(over="ignore"):  # float32 of a large float64: inf, still not native
        single = a.astype(np.float32)
    for odd, its_shape in ((single, shapes[k]), (a.astype(">f8"), shapes[k]),
                           (a.tolist(), shapes[k]), (a, (*shapes[k], 1)),
                           (np.zeros((2, 3))[:, ::2], (2, 2))):
        swapped = [*arrays]
        swapped[k] = odd
        shape_list = [*shapes]
        shape_list[k] = its_shape
        assert join_native(tuple(swapped), tuple(shape_list)) is None, (odd, its_shape)


def test_join_native_refuses_what_is_not_two_tuples() -> None:
    with pytest.raises(TypeError, match="arrays and shapes must be tuples of the same length"):
        join_native([np.zeros(3)], ((3,),))
    with pytest.raises(TypeError, match="shape 0 is not a tuple"):
        join_native((np.zeros(3),), ([3],))



def test_the_relay_columns_are_the_compiled_modules() -> None:
    """The wire reads a relay row by the columns ``_wire`` exports (``relay_row.h``, which the
    exchange's reader compiles too): they tile the row, and the wire's names are theirs."""
    fields = _wire.RELAY_FIELDS
    assert native.RELAY_FIELDS is fields
    assert [name for name, _, _ in fields] == ["position", "velocity", "sample_age", "held"]
    assert [start for _, start, _ in fields] == [0, *(stop for _, _, stop in fields[:-1])]
    assert fields[-1][2] == _wire.RELAY_WIDTH == wire.RELAY_WIDTH
    by_name = {name: (start, stop) for name, start, stop in fields}
    assert (wire.RELAY_POSITION.start, wire.RELAY_POSITION.stop) == by_name["position"]
    assert (native.RELAY_VELOCITY.start, native.RELAY_VELOCITY.stop) == by_name["velocity"]
    assert by_name["sample_age"] == (wire.RELAY_SAMPLE_AGE, wire.RELAY_SAMPLE_AGE + 1)
    assert by_name["held"] == (wire.RELAY_HELD, wire.RELAY_HELD + 1)


def test_a_relay_row_holds_each_beacons_values_in_their_columns() -> None:
    beacons = [(BeaconWire.build(j, 4, 0.1, (j, 2.0 * j, 3.0), velocity_m_s=(0.5, -j, 0.25),
                                 sample_age_s=0.01 * j), 0.3 * j) for j in (1, 2)]
    rows = BeaconRelayWire.build(4, beacons).rows()
    assert rows.shape == (2, _wire.RELAY_WIDTH)
    for row, (b, held_s) in zip(rows.tolist(), beacons, strict=True):
        columns = {name: row[start:stop] for name, start, stop in _wire.RELAY_FIELDS}
        assert columns == {"position": list(b.position_m), "velocity": list(b.velocity_m_s),
                           "sample_age": [b.sample_age_s], "held": [held_s]}
    assert BeaconRelayWire.build(4, []).data == b""
