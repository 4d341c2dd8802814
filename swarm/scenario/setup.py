"""What a run is set up from, given its config and seed: the random streams, where the drones
start, each drone's first guess of the targets, and each drone's ``DroneAgent``.

Every process of a swarm (the world, each agent) and the in-process reference draw from the
same streams, keyed so that drone i's numbers do not depend on how many other drones or
processes exist: the process swarm draws the very numbers the reference draws.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from swarm.core.drone_step import AgentSetup, DroneAgent
from swarm.core.formation import circle_bearings
from swarm.models.kinematics import InitialPlacementError, sample_initial_positions
from swarm.scenario.config import ConfigError, ScenarioConfig

Array = NDArray[np.float64]

# The purposes of the random streams (``stream``).
STREAM_INITIAL_POSITIONS = 1
STREAM_INITIAL_GUESS = 2
STREAM_CAMERA = 3


def stream(seed: int, purpose: int, index: int = 0) -> np.random.Generator:
    """The random stream of ``purpose`` for drone (or item) ``index`` of a run seeded ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(purpose, index)))


def initial_drone_positions(config: ScenarioConfig, seed: int) -> Array:
    """(N, 3) start positions [m] in the configured box, at least the minimum separation apart;
    ``ConfigError`` naming the file and key when this seed finds no such placement (the
    config's checks tried its own seed only)."""
    sw = config.swarm
    try:
        return sample_initial_positions(sw.n_drones, np.array(sw.initial_box_center_m),
                                        np.array(sw.initial_box_size_m),
                                        sw.initial_min_separation_m,
                                        stream(seed, STREAM_INITIAL_POSITIONS))
    except InitialPlacementError as err:
        raise ConfigError(f"{config.source}: swarm.initial_box_size_m: {err}") from None


def initial_target_guesses(config: ScenarioConfig, seed: int, drone_id: int) -> Array:
    """Truth at t = 0 plus U(−x, x) per axis, drawn from drone ``drone_id``'s own stream."""
    rng = stream(seed, STREAM_INITIAL_GUESS, drone_id)
    offset = config.estimation.initial_offset_m
    starts = np.array([t.start_m for t in config.targets], dtype=float)
    return starts + rng.uniform(-offset, offset, size=starts.shape)


def agent_setup(config: ScenarioConfig, drone_id: int) -> AgentSetup:
    """Drone ``drone_id``'s ``AgentSetup``: its neighbours' consensus weights, the parameters,
    and its desired bearings when the nominal task is a bearing formation."""
    graph = config.swarm.graph
    est = config.estimation
    desired: dict[int, Array] = {}
    if config.control.task == "bearing_formation":
        bearings = circle_bearings(graph.n_nodes)
        desired = {j: bearings[drone_id, j] for j in graph.neighbours[drone_id]}
    net = config.network
    if net.ranged:
        # Whoever the radio brings: every other drone may be a neighbour, each with the
        # weight 1/N, the largest that keeps every graph of N drones' update convex and
        # symmetric (docs/network.md).
        weights = {j: 1.0 / graph.n_nodes for j in range(graph.n_nodes) if j != drone_id}
    else:
        weights = graph.consensus_weights(drone_id, est.consensus_weights, est.laplacian_step)
    return AgentSetup(
        drone_id=drone_id,
        n_drones=graph.n_nodes,
        n_targets=len(config.targets),
        dt_s=config.scenario.dt_s,
        neighbour_weights=weights,
        perception=config.perception,
        estimation=est,
        gramian=config.gramian,
        control=config.control,
        desired_bearings=desired,
        safety=config.safety.params,
        network=net,
        kept_links=tuple(b if a == drone_id else a
                         for a, b in net.kept_edges(graph.n_nodes, graph.edges)
                         if drone_id in (a, b)),
    )


def build_agent(config: ScenarioConfig, seed: int, drone_id: int) -> DroneAgent:
    """Drone ``drone_id``'s core, as every mode builds it."""
    return DroneAgent(agent_setup(config, drone_id), initial_target_guesses(config, seed, drone_id))
