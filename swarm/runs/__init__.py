"""Runs: the in-process reference run, its record, ground-truth Gramians and the run checks."""
