"""swarm.observe.foxglove_scene: the swarm as Foxglove SceneUpdates, in every recording.

A recording of Case 2 is read back with the MCAP reader and the protobuf decoder of the MCAP
project, and every scene is checked against the run's truth and telemetry: the drones and the
targets where the truth has them, drones coloured by what their weights say, every estimate,
the FoV pyramids, the graph, the collision spheres, and the sim-time stamps.
"""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import numpy as np
import pytest
from foxglove.messages import LogLevel
from mcap.reader import make_reader
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from swarm.messages.wire import TelemetryCounters, TelemetryWire, TruthWire
from swarm.models.camera import fov_segments
from swarm.observe.foxglove_scene import (
    ELLIPSOID_PROBABILITY,
    ELLIPSOID_SIGMAS,
    ENTITIES,
    IDLE_COLOUR,
    SENSING_COLOUR,
    LogBook,
    SceneAssembler,
    SceneState,
    plot_topic,
    scene_update,
)
from swarm.observe.recording.reader import iter_messages
from swarm.observe.recording.writer import record_reference
from swarm.runs.checks import SENSING_WEIGHT
from swarm.runs.record import RunRecord
from swarm.scenario.config import load_config
from tests.helpers.scene_tools import decode_log, decode_scene, read_scenes
from tests.helpers.wire_samples import telemetry_message

ROOT = Path(__file__).resolve().parents[2]
CASE2 = ROOT / "configs" / "case2.toml"
DURATION_S = 4.0
SEED = 0


def _xyz(p) -> list[float]:
    return [p.x, p.y, p.z]


def _rgba(c) -> tuple[float, float, float, float]:
    return (c.r, c.g, c.b, c.a)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunRecord, list, Path]:
    config = load_config(CASE2).with_duration(DURATION_S)
    directory = tmp_path_factory.mktemp("scene")
    record = record_reference(config, SEED, directory)
    return record, read_scenes(directory), directory


def test_a_scene_every_tenth_of_a_second_in_foxglove_schema_and_sim_time(recorded) -> None:
    record, scenes, _ = recorded
    dt_ns = round(record.config.scenario.dt_s * 1e9)
    steps = [log_time // dt_ns for log_time, *_ in scenes]
    assert steps == list(range(0, record.n_steps, 5))  # 10 Hz at ΔT = 20 ms
    for log_time, schema, encoding, scene in scenes:
        assert (schema, encoding) == ("foxglove.SceneUpdate", "protobuf")
        assert [e.id for e in scene.entities] == list(ENTITIES)
        for entity in scene.entities:
            assert entity.frame_id == "world"
            assert entity.timestamp.seconds * 10**9 + entity.timestamp.nanos == log_time


def test_every_scene_holds_the_truth_and_what_the_drones_report(recorded) -> None:
    record, scenes, _ = recorded
    cfg = record.config
    dt_ns = round(cfg.scenario.dt_s * 1e9)
    n, m = record.drone_positions_m.shape[1], record.target_positions_m.shape[1]
    for log_time, _, _, scene in scenes:
        k = log_time // dt_ns
        entity = {e.id: e for e in scene.entities}
        drones = record.drone_positions_m[k]
        assert [_xyz(s.pose.position) for s in entity["drones"].spheres] == drones.tolist()
        assert [t.text for t in entity["drones"].texts] == [str(i) for i in range(n)]
        sensing = record.weights[k].max(axis=1) > SENSING_WEIGHT
        colours = [_rgba(s.color) for s in entity["drones"].spheres]
        np.testing.assert_allclose(colours, [SENSING_COLOUR if s else IDLE_COLOUR
                                             for s in sensing])
        assert [_xyz(s.pose.position) for s in entity["targets"].spheres] == \
            record.target_positions_m[k].tolist()
        assert [t.text for t in entity["targets"].texts] == [f"T{r}" for r in range(m)]
        estimates = record.estimates[k, :, :, :3].reshape(-1, 3)
        assert [_xyz(s.pose.position) for s in entity["estimates"].spheres] == \
            estimates.tolist()
        collision = entity["collision"].spheres
        assert [_xyz(s.pose.position) for s in collision] == drones.tolist()
        assert {s.size.x for s in collision} == {2 * cfg.control.collision_distance_m}
        (graph,) = entity["graph"].lines
        assert np.array([_xyz(p) for p in graph.points]).reshape(-1, 2, 3).tolist() == \
            [drones[[i, j]].tolist() for i, j in cfg.swarm.graph.edges]
        (fov,) = entity["fov"].lines
        ground_z = float(np.mean(record.target_positions_m[k, :, 2]))
        expected = [s for i in range(n)
                    for s in fov_segments(drones[i], cfg.camera.half_fov_deg,
                                          cfg.camera.range_max_m, ground_z)]
        np.testing.assert_allclose(np.array([_xyz(p) for p in fov.points]).reshape(-1, 2, 3),
                                   np.array(expected), atol=1e-12)


def test_each_estimate_carries_the_ellipsoid_of_the_covariance_its_drone_reported(
        recorded) -> None:
    """The ``uncertainty`` spheres, read back as axes (the size) and a rotation (the pose's
    quaternion), give back the position covariance each drone sent in its telemetry:
    R diag((size / 2k)²) Rᵀ = P⁺ with k = √(χ²₃ quantile), one ellipsoid per estimate."""
    record, scenes, directory = recorded
    quantile = float(np.sqrt(chi2.ppf(ELLIPSOID_PROBABILITY, 3)))
    assert abs(ELLIPSOID_SIGMAS - quantile) <= 1e-12 * quantile
    n, m = record.drone_positions_m.shape[1], record.target_positions_m.shape[1]
    covariance = {(rec.message.step, rec.drone): rec.message.estimate_covariance.to_array()
                  for rec in iter_messages(directory / "run.mcap", ("telemetry",))}
    dt_ns = round(record.config.scenario.dt_s * 1e9)
    largest_m = 0.0
    for log_time, _, _, scene in scenes:
        k = log_time // dt_ns
        (entity,) = [e for e in scene.entities if e.id == "uncertainty"]
        assert len(entity.spheres) == n * m
        for index, sphere in enumerate(entity.spheres):
            i, r = divmod(index, m)
            assert _xyz(sphere.pose.position) == record.estimates[k, i, r, :3].tolist()
            q = sphere.pose.orientation
            rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            variances = (np.array(_xyz(sphere.size)) / (2.0 * ELLIPSOID_SIGMAS)) ** 2
            expected = covariance[k, i][r]
            np.testing.assert_allclose(rotation @ np.diag(variances) @ rotation.T, expected,
                                       atol=1e-9 * np.abs(expected).max())
            largest_m = max(largest_m, float(np.max(_xyz(sphere.size))))
    assert largest_m > 0.0  # not all points: the filter's uncertainty shows


def test_an_estimate_without_a_covariance_has_no_ellipsoid() -> None:
    """An older recording (wire version 3) had no covariance: read back as NaN, drawn as no
    ellipsoid, the estimate itself still drawn."""
    config = load_config(CASE2)
    n, m = config.swarm.n_drones, len(config.targets)
    covariance = np.broadcast_to(np.diag([4.0, 1.0, 0.25]), (n, m, 3, 3)).copy()
    covariance[0, 1] = np.nan
    state = SceneState(step=0, time_s=0.0, drones_m=np.zeros((n, 3)),
                       targets_m=np.zeros((m, 3)), weights=np.zeros((n, m)),
                       estimates_m=np.ones((n, m, 3)), estimate_covariance_m2=covariance)
    entity = {e.id: e for e in decode_scene(scene_update(config, state)).entities}
    assert len(entity["estimates"].spheres) == n * m
    spheres = entity["uncertainty"].spheres
    assert len(spheres) == n * m - 1
    lengths = sorted(_xyz(spheres[0].size))  # the axes of diag(4, 1, 0.25): σ = 2, 1, 0.5
    np.testing.assert_allclose(lengths, 2 * ELLIPSOID_SIGMAS * np.array([0.5, 1.0, 2.0]))


def test_each_drones_plot_channel_holds_its_margins_weights_slacks_and_speed(
        recorded) -> None:
    record, scenes, directory = recorded
    config = record.config
    dt_ns = round(config.scenario.dt_s * 1e9)
    with (directory / "run.mcap").open("rb") as handle:
        plots = [(channel.topic, message.log_time, json.loads(message.data))
                 for _, channel, message in make_reader(handle).iter_messages(
                     topics=[plot_topic(i) for i in range(config.swarm.n_drones)])]
    assert len(plots) == len(scenes) * config.swarm.n_drones
    for topic, log_time, values in plots:
        k, i = log_time // dt_ns, int(topic.split("/")[1])
        assert values["time_s"] == pytest.approx(k * config.scenario.dt_s)
        assert values["lambda_margin"] == record.psi0[k, i].tolist()
        assert values["weights"] == record.weights[k, i].tolist()
        assert values["slacks"] == record.slacks[k, i].tolist()
        assert values["speed_m_s"] == pytest.approx(
            float(np.linalg.norm(record.velocities_m_s[k, i])), rel=1e-12)


def test_a_drone_whose_weights_are_all_low_is_drawn_idle() -> None:
    config = load_config(CASE2)
    n, m = config.swarm.n_drones, len(config.targets)
    weights = np.zeros((n, m))
    weights[0, 1] = SENSING_WEIGHT + 1e-9
    weights[1, 0] = SENSING_WEIGHT  # not above the threshold: idle
    state = SceneState(step=0, time_s=0.0, drones_m=np.arange(3 * n, dtype=float).reshape(n, 3),
                       targets_m=np.zeros((m, 3)), weights=weights,
                       estimates_m=np.zeros((n, m, 3)))
    drones = decode_scene(scene_update(config, state)).entities[0]
    assert drones.id == "drones"
    np.testing.assert_allclose([_rgba(s.color) for s in drones.spheres],
                               [SENSING_COLOUR] + [IDLE_COLOUR] * (n - 1))


def _truth(step: int, n: int = 2, m: int = 1) -> TruthWire:
    return TruthWire.build(step, 0.02 * step, np.zeros((n, 3)), np.ones((m, 3)),
                           np.zeros((m, 3)))


_SAMPLE = telemetry_message()  # a real agent step's telemetry (2 targets, as Case 2)


def _telemetry(step: int, drone: int) -> TelemetryWire:
    return msgspec.structs.replace(_SAMPLE, step=step, drone=drone)


def test_the_envelope_is_drawn_from_the_config_and_only_when_there_is_one() -> None:
    """configs/case2_envelope.toml: the keep-in box's 4 edges at the floor and at the
    ceiling and a post at each corner (12 segments), the obstacle as a cylinder from floor to
    ceiling; Case 2 (no envelope): an empty entity."""
    config = load_config(ROOT / "configs" / "case2_envelope.toml")
    n, m = config.swarm.n_drones, len(config.targets)
    state = SceneState(step=0, time_s=0.0, drones_m=np.zeros((n, 3)),
                       targets_m=np.zeros((m, 3)), weights=np.zeros((n, m)),
                       estimates_m=np.zeros((n, m, 3)))
    entity = {e.id: e for e in decode_scene(scene_update(config, state)).entities}["envelope"]
    (lines,) = entity.lines
    segments = np.array([_xyz(p) for p in lines.points]).reshape(-1, 2, 3)
    safety = config.safety
    x0, y0, x1, y1 = safety.keep_in_box_m
    corners = {(x0, y0), (x1, y0), (x1, y1), (x0, y1)}
    assert len(segments) == 12
    assert {(float(x), float(y)) for x, y in segments[..., :2].reshape(-1, 2)} == corners
    assert set(segments[..., 2].ravel().tolist()) == {safety.floor_m, safety.ceiling_m}
    (cylinder,) = entity.cylinders
    (obstacle,) = safety.keep_out
    assert _xyz(cylinder.pose.position) == [*obstacle.center_m,
                                            (safety.floor_m + safety.ceiling_m) / 2]
    assert _xyz(cylinder.size) == [2 * obstacle.radius_m, 2 * obstacle.radius_m,
                                   safety.ceiling_m - safety.floor_m]
    plain = load_config(CASE2)
    empty = {e.id: e for e in decode_scene(scene_update(plain, state)).entities}["envelope"]
    assert (list(empty.lines), list(empty.cylinders)) == ([], [])


def test_the_assembler_waits_for_every_drone_and_gives_up_stale_steps() -> None:
    config = load_config(CASE2)
    n, m = config.swarm.n_drones, len(config.targets)
    got: list[SceneState] = []
    assembler = SceneAssembler(config, got.append, period_steps=5)
    assembler.on_truth(_truth(3, n, m))  # not a scene step: ignored
    for drone in range(n - 1):  # step 5: one drone's telemetry missing
        assembler.on_telemetry(_telemetry(5, drone))
    assembler.on_truth(_truth(5, n, m))
    assert got == []
    for drone in reversed(range(n)):  # step 10 in any order, truth last
        assembler.on_telemetry(_telemetry(10, drone))
    assembler.on_truth(_truth(10, n, m))
    assert [s.step for s in got] == [10]
    assert (assembler.emitted, assembler.incomplete) == (1, 1)  # step 5 given up
    assembler.on_telemetry(_telemetry(5, n - 1))  # too late: a new, lone slot
    assert [s.step for s in got] == [10]


def test_the_log_book_says_which_counters_rose_and_how_badly() -> None:
    config = load_config(CASE2)
    n, m = config.swarm.n_drones, len(config.targets)
    quiet = TelemetryCounters()

    def state(step: int, counters: tuple[TelemetryCounters, ...]) -> SceneState:
        return SceneState(step=step, time_s=0.02 * step, drones_m=np.zeros((n, 3)),
                          targets_m=np.zeros((m, 3)), weights=np.zeros((n, m)),
                          estimates_m=np.zeros((n, m, 3)), counters=counters)

    book = LogBook()
    assert book.lines(state(0, (quiet,) * n)) == []
    late = msgspec.structs.replace(quiet, late_steps=3)
    breach = msgspec.structs.replace(quiet, lambda_breaches=1,
                                     localization_status="T1 below the floor")
    lines = [decode_log(line) for line in
             book.lines(state(5, (late, quiet, breach) + (quiet,) * (n - 3)))]
    assert [(line.name, line.level, line.message) for line in lines] == [
        ("drone 0", LogLevel.Warning.value, "+3 late steps (3 total)"),
        ("drone 2", LogLevel.Error.value,
         "+1 targets its λ̄ copy let fall below ε − tol (1 total); now: T1 below the floor")]
    assert lines[0].timestamp.seconds * 10**9 + lines[0].timestamp.nanos == 100_000_000
    assert book.lines(state(10, (late, quiet, breach) + (quiet,) * (n - 3))) == []
