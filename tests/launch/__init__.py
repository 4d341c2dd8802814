"""Tests of swarm.launch: launch-swarm end to end, on the emulator and on real autopilots."""
