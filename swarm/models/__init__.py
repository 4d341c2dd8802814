"""Pure scenario and physics models: targets, cameras, vehicle kinematics, the ENU/NED and
geodetic frames, and the command reference a vehicle is sent to follow."""
