"""Tests of swarm.models."""
