"""Tests of swarm.scenario."""
