"""Tests of swarm.runs: the thesis' cases run in process."""
