"""Tests of swarm.messages."""
