"""Tests of swarm.observe."""
