"""An observer's view of a run, in one place: a client session on the world's router and
the subscriptions an observer holds (the launcher, the dashboard, a remote recorder).

``join_router(endpoints, timeout_s, ...)`` retries while the world starts up;
``subscribe_observer(session, keys, codec, rejections, ...)`` subscribes to telemetry and the
clock, and to the truth, the beacons and the camera frames for whoever passes a callback.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from swarm.messages.wire import (
    BeaconWire,
    CameraFrameWire,
    ClockWire,
    TelemetryWire,
    TruthWire,
    WireCodec,
)
from swarm.net.security import TlsIdentity
from swarm.net.transport import (
    Keys,
    RejectionCounter,
    TransportError,
    open_session,
    subscribe,
    zenoh_config,
)

OnMessage = Callable[[str, Any], None]


def join_router(endpoints: Sequence[str], timeout_s: float, *, tls: TlsIdentity | None = None,
                connect_timeout_s: float | None = None,
                before_each_try: Callable[[], None] = lambda: None,
                pause: Callable[[float], Any] = time.sleep) -> zenoh.Session:
    """A client session on the router at ``endpoints``, tried every 0.1 s (``pause``) until
    ``timeout_s`` has passed; then the last ``TransportError``. ``before_each_try`` may raise
    to give up sooner (the launcher: a child died)."""
    deadline = time.monotonic() + timeout_s
    while True:
        before_each_try()
        try:
            return open_session(zenoh_config(mode="client", connect=list(endpoints),
                                             connect_timeout_s=connect_timeout_s, tls=tls))
        except TransportError:
            if time.monotonic() > deadline:
                raise
        pause(0.1)


def subscribe_observer(session: zenoh.Session, keys: Keys, codec: WireCodec,
                       rejections: RejectionCounter, *,
                       on_telemetry: Callable[[str, TelemetryWire], None],
                       on_clock: Callable[[str, ClockWire], None],
                       on_truth: Callable[[str, TruthWire], None] | None = None,
                       on_beacon: Callable[[str, BeaconWire], None] | None = None,
                       on_camera: Callable[[str, CameraFrameWire], None] | None = None
                       ) -> list[Any]:
    """Subscribe to every drone's telemetry and the world's clock, and to the truth, the
    beacons and the camera frames where a callback is given; each payload decoded by
    ``codec``, each rejection counted in ``rejections`` under its kind. Keep the returned
    subscribers: a subscription lives as long as its handle."""
    wanted: list[tuple[str, Callable[[bytes], Any], OnMessage | None, str]] = [
        (keys.all_telemetry, codec.decode_telemetry, on_telemetry, "telemetry"),
        (keys.truth, codec.decode_truth, on_truth, "truth"),
        (keys.clock, codec.decode_clock, on_clock, "clock"),
        (keys.all_beacons, codec.decode_beacon, on_beacon, "beacon"),
        (keys.all_cameras, codec.decode_camera, on_camera, "camera"),
    ]
    return [subscribe(session, key, decode, callback, rejections, kind)
            for key, decode, callback, kind in wanted if callback is not None]
