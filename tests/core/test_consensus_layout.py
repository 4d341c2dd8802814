"""The packed consensus layout: its slices tile x in the documented order, pack and unpack
are each other's inverse."""

from __future__ import annotations

import numpy as np
import pytest

from swarm.core.consensus_layout import ConsensusLayout

ORDER = ("projector_mean", "weight_mean", "projector_integral", "weight_integral", "gramian")
SIZES = {"projector_mean": 9, "weight_mean": 1, "projector_integral": 9, "weight_integral": 1,
         "gramian": 9}


@pytest.mark.parametrize("m", [1, 2, 3, 5])
def test_slices_tile_the_vector_in_order(m: int) -> None:
    layout = ConsensusLayout(m)
    assert layout.size == 29 * m
    position = 0
    for name in ORDER:
        part = getattr(layout, name)
        assert (part.start, part.stop) == (position, position + SIZES[name] * m), name
        position = part.stop
    assert position == layout.size
    assert (layout.means.start, layout.means.stop) == (0, layout.weight_mean.stop)
    assert (layout.integrals.start, layout.integrals.stop) == (
        layout.projector_integral.start, layout.weight_integral.stop)
    assert [layout.target_projector_mean(r) for r in range(m)] == [
        slice(9 * r, 9 * r + 9) for r in range(m)]


@pytest.mark.parametrize("m", [1, 2, 3])
def test_pack_and_unpack_are_inverse(m: int) -> None:
    layout = ConsensusLayout(m)
    rng = np.random.default_rng(m)
    states = {"projector_mean": rng.normal(size=(m, 3, 3)), "weight_mean": rng.normal(size=m),
              "projector_integral": rng.normal(size=(m, 3, 3)),
              "weight_integral": rng.normal(size=m), "gramian": rng.normal(size=(m, 3, 3))}
    x = np.concatenate(layout.pack(*(states[name] for name in ORDER)))
    assert x.shape == (layout.size,)
    back = layout.unpack(x)
    assert set(back) == set(ORDER)
    for name in ORDER:
        assert np.array_equal(back[name], states[name]), name
    # row-major 3×3 blocks, target by target
    assert np.array_equal(x[layout.target_projector_mean(m - 1)],
                          states["projector_mean"][m - 1].ravel())
