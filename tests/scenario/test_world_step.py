"""The scene of a step (swarm.scenario.world_step): the truth of the trajectories, each drone's
frames from its own stream, the same in every process that renders it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from swarm.models.camera import detect
from swarm.scenario.config import load_config
from swarm.scenario.overrides import parse_assignment
from swarm.scenario.setup import STREAM_CAMERA, initial_drone_positions, stream
from swarm.scenario.world_step import Scene
from swarm.vision.detect import MarkerDetector

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
CASE2 = CONFIGS / "case2.toml"
# Case 1's drones at its seed-0 start (every target in some camera's view).
START = initial_drone_positions(load_config(CONFIGS / "case1.toml"), 0)


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


# -- a rendered camera (camera.model = "rendered", issue 45) --------------------------------


def rendered_case1(*assignments: str):
    return load_config(CONFIGS / "case1.toml", overrides=[
        parse_assignment(a) for a in ('camera.model="rendered"', *assignments)])


def test_the_bearing_camera_renders_nothing() -> None:
    view = Scene(load_config(CONFIGS / "case1.toml"), seed=0).at(0, START)
    assert view.images is None and view.rejected == []


def test_a_rendered_camera_frames_at_its_rate_and_its_detections_are_the_detectors() -> None:
    """10 Hz on 50 Hz steps: a frame every 5th step, none between; each frame's detections
    are the marker detector's on that encoded frame; the same seed, the same frames."""
    config = rendered_case1("camera.frame_rate_hz=10.0")
    scene, again = Scene(config, seed=3), Scene(config, seed=3)
    detector = MarkerDetector(config.camera, scene.renderer.calibration, len(config.targets))
    for k in range(11):
        view, twin = scene.at(k, START), again.at(k, START)
        if k % 5:
            assert view.images is None and all(d == [] for d in view.detections)
            continue
        assert view.images is not None and len(view.images) == config.swarm.n_drones
        assert view.images == twin.images
        for i, image in enumerate(view.images):
            found = detector.detect_encoded(image)
            assert [d.target for d in view.detections[i]] == [d.target for d in found.detections]
            for ours, theirs in zip(view.detections[i], found.detections, strict=True):
                assert np.array_equal(ours.image_point, theirs.image_point)
            assert view.rejected[i] == found.rejected
    assert any(view.detections[i] for i in range(config.swarm.n_drones))


def test_the_world_process_scene_renders_without_detecting() -> None:
    config = rendered_case1()
    view = Scene(config, seed=0).at(0, START, detect_markers=False)
    assert view.images is not None and view.detections == [[]] * config.swarm.n_drones
    assert view.rejected == []
