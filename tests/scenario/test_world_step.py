"""The scene of a step (swarm.scenario.world_step): the truth of the trajectories, each drone's
frames from its own stream, the same in every process that renders it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from swarm.models.camera import detect
from swarm.scenario.config import load_config
from swarm.scenario.setup import STREAM_CAMERA, initial_drone_positions, stream
from swarm.scenario.world_step import Scene

CASE2 = Path(__file__).resolve().parents[2] / "configs" / "case2.toml"


def test_a_step_is_the_truth_and_each_drones_own_noisy_frames() -> None:
    config = load_config(CASE2)
    scene, positions = Scene(config, 7), initial_drone_positions(config, 7)
    cameras = [stream(7, STREAM_CAMERA, i) for i in range(config.swarm.n_drones)]
    for k in (0, 1, 2):
        view = scene.at(k, positions)
        t = k * config.scenario.dt_s
        assert view.step == k and view.time_s == t
        truth = np.array([target.build().position(t) for target in config.targets])
        np.testing.assert_array_equal(view.target_positions_m, truth)
        for i, frame in enumerate(view.detections):
            expected = detect(positions[i], truth, config.camera, cameras[i])
            assert [d.target for d in frame] == [d.target for d in expected]
            for got, want in zip(frame, expected, strict=True):
                np.testing.assert_array_equal(got.image_point, want.image_point)
    assert any(view.detections)  # Case 2's drones see a target at the start


def test_a_drones_frames_do_not_depend_on_where_the_others_are() -> None:
    config = load_config(CASE2)
    positions = initial_drone_positions(config, 0)
    moved = positions.copy()
    moved[1:] += 5.0
    a, b = Scene(config, 0).at(0, positions), Scene(config, 0).at(0, moved)
    assert [d.target for d in a.detections[0]] == [d.target for d in b.detections[0]]
    for got, want in zip(a.detections[0], b.detections[0], strict=True):
        np.testing.assert_array_equal(got.image_point, want.image_point)


def test_frames_carry_the_target_velocities_only_for_the_single_integrator() -> None:
    config = load_config(CASE2)
    positions = initial_drone_positions(config, 0)
    for model, carried in (("single_integrator", True), ("double_integrator", False)):
        changed = dataclasses.replace(config, estimation=dataclasses.replace(
            config.estimation, model=model))
        view = Scene(changed, 0).at(3, positions)
        if carried:
            np.testing.assert_array_equal(view.communicated_velocities_m_s,
                                          view.target_velocities_m_s)
        else:
            assert view.communicated_velocities_m_s is None
