"""Pure scenario and physics models: targets, cameras, vehicle kinematics and the ENU/NED frames."""
