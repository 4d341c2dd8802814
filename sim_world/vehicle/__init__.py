"""An emulated MAVLink 2 vehicle, PX4 or ArduCopter flavour, as a pure protocol state machine
(SPEC §12): bytes in, bytes out, every time given by the caller, so that ``sim-world`` drives
the same object in both time modes and the tests drive it without any network.

- ``flavours``: what differs between the two firmwares (modes, parameters, the timings of
  their automatic flight, default streams);
- ``flight``: how the copter flies (modes, guidance, failsafes, landing, auto-disarm);
- ``protocol``: its MAVLink side, ``EmulatedVehicle`` (parsing, commands, parameters,
  telemetry, signing, the stamps of lockstep setpoints).

The public API and the behaviour of both flavours, with where each figure comes from:
docs/vehicle_emulator.md.
"""

from sim_world.mavlink_endpoint import VehicleEndpoint
from sim_world.vehicle.flavours import (
    FLIGHT_MODELS,
    MEASURED_RESPONSE,
    Flavour,
    FlightModel,
    Start,
)
from sim_world.vehicle.protocol import (
    AUTOPILOT_COMPONENT_ID,
    SYS_STATUS_SENSORS,
    EmulatedVehicle,
    PacketCollector,
)

__all__ = [
    "AUTOPILOT_COMPONENT_ID",
    "FLIGHT_MODELS",
    "MEASURED_RESPONSE",
    "SYS_STATUS_SENSORS",
    "EmulatedVehicle",
    "Flavour",
    "FlightModel",
    "PacketCollector",
    "Start",
    "VehicleEndpoint",
]
