"""A process swarm's record against the in-process reference run of the same config and seed."""

from __future__ import annotations

import numpy as np

from swarm.runs.reference import run_reference

COMPARED = ("drone_positions_m", "velocities_m_s", "estimates", "lambda_bar", "weights",
            "target_positions_m")


def assert_matches_reference(config, record, seed: int):
    """``record`` equals the in-process run of ``config`` to 1e-9; that run, for more checks."""
    reference = run_reference(config, seed=seed)
    for name in COMPARED:
        ours, theirs = getattr(record, name), getattr(reference, name)
        assert ours.shape == theirs.shape, name
        assert np.max(np.abs(ours - theirs)) <= 1e-9, name
    return reference
