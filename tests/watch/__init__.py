"""Tests of swarm.watch."""
