"""Tests of swarm.net: real Zenoh sessions between real processes."""
