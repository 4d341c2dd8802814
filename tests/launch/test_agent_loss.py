"""Losing an agent in a realtime mission (issue 6, point 1): real processes, Zenoh, MAVLink.

``kill -9`` of one agent in the middle of Case 2: the launcher reports it and the mission goes
on; the lost drone's vehicle holds within its failsafe time; its neighbours leave it out of
their consensus sums within the stale timeout; every survivor's N drops to 5 within the
membership timeout; λ̄ of the target it mattered most for comes back to ≥ ε − 0.04 within
15 s; the launcher restarts it with the same id and it rejoins (N back to 6 everywhere).
Throughout, every drone's telemetry says at the very step one of its λ̄ copies is below
ε − tol, and only then (``swarm.watch.localization_watch``, issue 14 point 5).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.messages.wire import TelemetryWire
from swarm.scenario.config import load_config

pytestmark = pytest.mark.wallclock

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
KILL_AT_S = 12.0
OUTAGE_S = 18.0  # restart delay: λ̄ must recover with the survivors alone first
DURATION_S = 42.0


class TelemetryLog:
    """Per drone, per step: λ̄ copies, N in use, consensus sums run without a neighbour."""

    def __init__(self, floor: float) -> None:
        self.floor = floor  # ε − tol: a λ̄ copy below it is a breach its drone must say
        self.lock = threading.Lock()
        self.lambda_bar: dict[int, dict[int, np.ndarray]] = defaultdict(dict)
        self.swarm_size: dict[int, dict[int, int]] = defaultdict(dict)
        self.missing: dict[int, dict[int, int]] = defaultdict(dict)
        # (said, truly below): the drone's telemetry says a copy is below ε − tol, and it is.
        self.said: dict[int, dict[int, tuple[bool, bool]]] = defaultdict(dict)

    def __call__(self, tel: TelemetryWire) -> None:
        with self.lock:
            self.lambda_bar[tel.drone][tel.step] = tel.arrays()["lambda_bar"]
            self.swarm_size[tel.drone][tel.step] = tel.counters.swarm_size
            self.missing[tel.drone][tel.step] = tel.missing_neighbour_messages
            below = tel.control_active and bool(np.any(tel.arrays()["lambda_bar"] < self.floor))
            self.said[tel.drone][tel.step] = (bool(tel.counters.localization_status), below)

    def steps(self, drone: int, first: int, last: int) -> list[int]:
        return sorted(k for k in self.swarm_size[drone] if first <= k <= last)


@pytest.mark.slow
def test_a_killed_agent_leaves_the_swarm_which_recovers_and_it_rejoins(tmp_path: Path) -> None:
    path = CONFIGS / "case2.toml"
    config = load_config(path).with_duration(DURATION_S)
    dt, epsilon = config.scenario.dt_s, config.gramian.epsilon
    runtime, graph = config.runtime, config.swarm.graph
    lines: list[str] = []
    launcher = SwarmLauncher(LaunchOptions(
        config=config, config_path=str(path), seed=0, mode="realtime", log_dir=tmp_path,
        agent_restarts=1, agent_restart_delay_s=OUTAGE_S), log=lines.append)
    telemetry = TelemetryLog(epsilon - config.checks.lambda_tolerance)
    outcome: dict = {}

    def run() -> None:
        try:
            outcome["record"] = launcher.run(telemetry_listeners=[telemetry])
        except Exception as err:  # reported by the assertion below
            outcome["error"] = err

    runner = threading.Thread(target=run)
    runner.start()
    try:
        deadline = time.monotonic() + 60.0
        kill_step = round(KILL_AT_S / dt)
        while launcher.collector.last_truth_step < kill_step:
            assert runner.is_alive() and time.monotonic() < deadline, (outcome, lines)
            time.sleep(0.01)
        # The drone that matters most: the largest perception weight on any target now.
        with launcher.collector.lock:
            weights = launcher.collector.weights[launcher.collector.last_truth_step - 5].copy()
        victim, target = np.unravel_index(np.nanargmax(weights), weights.shape)
        victim, target = int(victim), int(target)
        kill_step = launcher.collector.last_truth_step
        agent = next(c for c in launcher.children if c.drone == victim)
        os.kill(agent.process.pid, signal.SIGKILL)
    finally:
        runner.join(timeout=DURATION_S + 60.0)
    assert "error" not in outcome, (outcome, lines)
    record = outcome["record"]

    # The launcher reported the loss, went on, and restarted the drone.
    assert [(loss.drone, loss.how, loss.restarted) for loss in launcher.agent_losses] == [
        (victim, "signal 9", True)]
    assert any(f"drone {victim} lost" in line and "goes on without it" in line
               for line in lines), lines
    assert any(f"drone {victim} restarted" in line for line in lines), lines
    restart_step = kill_step + round(OUTAGE_S / dt)
    # The victim's last step: its last telemetry before the restart. ``kill_step`` is the
    # world's step as the launcher had received it when the signal went out; on a busy
    # machine the swarm can be steps ahead of that (a CI run measured the neighbours' drop 12
    # steps after it; on a quiet one the victim's last step is kill_step and the drop comes
    # 5-6 steps later). The stale timeout runs from the victim's last message.
    last_alive = max(telemetry.steps(victim, 0, restart_step - 1))

    # The vehicle holds within its failsafe time: it does not move from then to the restart.
    hold = last_alive + round((config.vehicles.failsafe_timeout_s + 0.1) / dt)
    held = record.drone_positions_m[hold:restart_step, victim]
    assert np.abs(held - held[0]).max() < 1e-9

    survivors = [i for i in range(config.swarm.n_drones) if i != victim]
    for i in survivors:
        # Neighbours leave it out of the consensus within the stale timeout (+ two steps).
        if victim in graph.neighbours[i]:
            # The victim's last message is of its last telemetry's step or of the next one:
            # an agent sends its beacon and consensus rounds during a step and its telemetry
            # at the end, and SIGKILL can land in between (a CI run: last telemetry 599,
            # kill step 600, drop at 607, i.e. 5 + 2 steps after 600).
            last_message = last_alive + 1
            dropped = min(k for k, missing in telemetry.missing[i].items()
                          if k > last_alive and missing > 0)
            assert (dropped - last_message) * dt <= runtime.stale_timeout_s + 2 * dt, (
                i, dropped, last_alive, kill_step)
        # N follows the membership: 5 from the membership timeout on, until the restart.
        sizes = {k: telemetry.swarm_size[i][k] for k in telemetry.steps(
            i, kill_step + round((runtime.member_timeout_s + 0.2) / dt), restart_step - 1)}
        assert set(sizes.values()) == {5}, (i, sorted(set(sizes.values())))

    # λ̄ of every survivor's copy for the lost drone's target is back to ≥ ε − 0.04 within
    # 15 s and stays there while the drone is away; the copies agree.
    back_by = kill_step + round(15.0 / dt)
    copies = np.array([[telemetry.lambda_bar[i][k][target] for i in survivors]
                       for k in range(back_by, restart_step)
                       if all(k in telemetry.lambda_bar[i] for i in survivors)])
    assert len(copies) > 0.9 * (restart_step - back_by)
    assert copies.min() >= epsilon - 0.04, copies.min()
    # The survivors' copies agree by the end of the outage within the tolerance the run's
    # checks allow λ̄ (right after the loss they drift apart while N and the sums settle:
    # 0.039 at +15 s in one CI run; 0.0025-0.010 in the last second before the restart,
    # against 0.008-0.014 among all six before the loss).
    tail = copies[-round(1.0 / dt):]
    assert np.ptp(tail, axis=1).max() <= config.checks.lambda_tolerance

    # Every drone says it at the very step one of its λ̄ copies is below ε − tol, and only
    # then (swarm.watch.localization_watch), before, during and after the loss.
    for i in range(config.swarm.n_drones):
        wrong = [k for k, (said, below) in telemetry.said[i].items() if said != below]
        assert not wrong, (i, wrong[:5])

    # The restarted agent rejoins: it steps again and everyone counts six drones again.
    end = record.n_steps - 1
    rejoined = end - round(3.0 / dt)
    assert telemetry.steps(victim, rejoined, end)
    for i in range(config.swarm.n_drones):
        sizes = {telemetry.swarm_size[i][k] for k in telemetry.steps(i, rejoined, end)}
        assert sizes == {6}, (i, sizes)
