"""The simulated world: targets, cameras and drone kinematics (and, later, MAVLink vehicles)."""
