"""Sweeps: many missions from one file, on Dask distributed (``swarm-sweep``)."""
