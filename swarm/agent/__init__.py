"""The agent process: one drone's loop around the core, its Zenoh peers and its autopilot link."""
