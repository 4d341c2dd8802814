"""MAVLink: the autopilot link, message parsing, signing, PX4 events and SITL firmware."""
