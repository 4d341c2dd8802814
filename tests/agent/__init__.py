"""Tests of swarm.agent."""
