"""The wire's compiled work on float64 bytes (``swarm/messages/_wire.c``) and the columns of a
relayed beacon's row.

``native_finite(*parts)``: whether every float64 of native-order bytes is finite, the wire
rules' check of every float a peer sends (``swarm.messages.rules``, ``swarm.messages.wire``).
``join_native(arrays, shapes)``: ``b"".join(a.tobytes() for a in arrays)`` when every array is
a C-contiguous native float64 array of its shape in ``shapes``, else None: the telemetry's
packing of a step's arrays. ``tests/messages/test_native.py`` binds both to their numpy forms.

``RELAY_*``: the columns of a ``BeaconRelayWire`` row, as the C source states them
(``relay_row.h``) for the wire and for the exchange's compiled reader (``swarm.agent.nearby``).

The extension is built by ``pip install -e .`` (setuptools, the machine's C compiler).
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

from swarm.compiled import (
    Field,
    check_built_from_current_source,
    field_index,
    field_slice,
    not_built,
)

try:
    from swarm.messages import _wire
except ImportError as exc:  # pragma: no cover - a source tree that was never installed
    raise not_built("swarm.messages._wire", "swarm/messages/_wire.c") from exc

_HERE = Path(__file__).parent
RELAY_ROW_HEADER: Final = _HERE / "relay_row.h"
check_built_from_current_source(Path(_wire.__file__), _HERE / "_wire.c", RELAY_ROW_HEADER,
                                _HERE.parent / "compiled.h")

native_finite = _wire.native_finite
join_native = _wire.join_native

# A relayed beacon's row in ``BeaconRelayWire.data``: position (3) and velocity (3), the
# sample's age when the drone sent it, and how long the world had held it when the relay left.
RELAY_FIELDS: Final[tuple[Field, ...]] = _wire.RELAY_FIELDS
RELAY_POSITION: Final = field_slice(RELAY_FIELDS, "position")
RELAY_VELOCITY: Final = field_slice(RELAY_FIELDS, "velocity")
RELAY_SAMPLE_AGE: Final = field_index(RELAY_FIELDS, "sample_age")
RELAY_HELD: Final = field_index(RELAY_FIELDS, "held")
RELAY_WIDTH: Final[int] = _wire.RELAY_WIDTH
