"""Tests of swarm.mavlink, against real autopilot firmware where it is present."""
