"""Losing a drone (issue 14, point 5): λ̄ after the loss of each drone, and whether the
survivors said so at once.

    python benchmarks/drone_loss.py [--vehicles emulator ardupilot] [--case case1 case2]
        [--drones 3 6] [--kill-at 12] [--duration S] [--seed 0] [--baseline]
        [--json out.json] [--keep DIR]

Each run is the command a user runs, ``launch-swarm configs/<case>.toml --mode realtime
--headless --record DIR --kill-agent V@T`` (``--sitl ardupilot`` for the ArduCopter SITL of
``../shared/autopilots/`` or ``$VIGIL_ARDUCOPTER``; the emulated vehicles of the config
otherwise), for every victim V of the swarm, one mission at a time. N = 3 is the case with
``swarm.n_drones = 3`` and a triangle graph (as ``tests/configs/case1_three.toml``);
``--baseline`` adds a run without a loss per case and N.

From each recording, over the survivors and the steps from the loss on: the smallest λ̄ − ε
(per target), how long some survivor's copy stayed below ε − tol, the verdict of the run's
checks, the smallest pairwise distance, the survivors' final estimate error; and what the
survivors said (``lambda_breaches`` in their telemetry) against what their copies did: the
delay from the first copy below ε − tol to the first agent saying so (0 s = the same step);
and the first survivor QP fallback from the loss on (the hard QP had no solution: the barrier
was no longer enforced), which comes before a breach.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.sitl_soak import fly_and_measure  # noqa: E402
from swarm.observe.recording import iter_messages, read_recording  # noqa: E402
from swarm.runs.checks import check_invariants, min_pairwise_distance, start_index  # noqa: E402
from tests.helpers.sitl_tools import find_firmware  # noqa: E402

TRIANGLE = [[0, 1], [1, 2], [2, 0]]


def write_config(case: str, n_drones: int, duration: float | None, directory: Path) -> Path:
    """configs/<case>.toml as JSON, cut to ``n_drones`` (3: a triangle graph)."""
    data = tomllib.loads((ROOT / "configs" / f"{case}.toml").read_text())
    if n_drones != data["swarm"]["n_drones"]:
        if n_drones != 3:
            raise SystemExit(f"drone_loss: N = {n_drones}: only the config's own N or 3")
        data["swarm"].update(n_drones=3, edges=TRIANGLE)
        data["scenario"]["name"] = f"{case}_three"
    if duration is not None:
        data["scenario"]["duration_s"] = duration
    path = directory / f"{case}_{n_drones}.json"
    path.write_text(json.dumps(data))
    return path


def measure(recording: Path, victim: int | None) -> dict[str, object]:
    """Figures of one mission after the loss of ``victim`` (None: from control start)."""
    rec = read_recording(recording, fill_gaps=True)
    record, config = rec.record, rec.config
    eps, tol, dt = config.gramian.epsilon, config.checks.lambda_tolerance, config.scenario.dt_s
    n = config.swarm.n_drones
    survivors = [i for i in range(n) if i != victim]
    said_step: dict[int, int] = {}
    last: dict[int, object] = {}
    victim_last = -1
    fallback_steps: list[int] = []
    for item in iter_messages(recording, ("telemetry",)):
        tel = item.message
        last[tel.drone] = tel.counters
        if tel.drone == victim:
            victim_last = max(victim_last, tel.step)
            continue
        if tel.counters.lambda_breaches and tel.drone not in said_step:
            said_step[tel.drone] = tel.step
        if tel.qp_fallback:
            fallback_steps.append(tel.step)
    loss = victim_last + 1 if victim is not None else start_index(record)
    lam = record.lambda_bar[loss:, survivors, :]  # (K', S, M)
    margins = [float(np.nanmin(lam[:, :, r]) - eps) for r in range(lam.shape[2])]
    below = np.any(lam < eps - tol, axis=(1, 2))
    first_below = int(np.argmax(below)) + loss if below.any() else None
    first_said = min((k for i, k in said_step.items() if i in survivors), default=None)
    first_fallback = min((k for k in fallback_steps if k >= loss), default=None)
    end = record.n_steps - 1
    errors = [float(np.linalg.norm(record.estimates[end, i, r, :3]
                                   - record.target_positions_m[end, r]))
              for i in survivors for r in range(record.target_positions_m.shape[1])
              if np.all(np.isfinite(record.estimates[end, i, r, :3]))]
    violations = check_invariants(record)
    return {
        "loss_s": round(loss * dt, 2),
        "min_margin_per_target": margins,
        "min_margin": min(margins),
        "lambda_tolerance": tol,
        "below_s": round(float(below.sum()) * dt, 2),
        "first_below_s": None if first_below is None else round(first_below * dt, 2),
        "first_said_s": None if first_said is None else round(first_said * dt, 2),
        "said_delay_s": (None if first_below is None or first_said is None
                         else round((first_said - first_below) * dt, 2)),
        "first_fallback_s": None if first_fallback is None else round(first_fallback * dt, 2),
        "breaches_said": int(sum(last[i].lambda_breaches for i in survivors if i in last)),
        "ok": not violations,
        "violations": [f"{v.invariant}: {v.detail}" for v in violations],
        "min_distance_m": float(min_pairwise_distance(record)),
        "final_error_m": max(errors) if errors else math.nan,
        "qp_fallbacks": int(sum(c.qp_fallbacks for c in last.values())),
    }


def run_mission(config: Path, vehicles: str, firmware: Path | None, victim: int | None,
                kill_at: float, seed: int, directory: Path) -> dict[str, object]:
    victim_name = "none" if victim is None else victim
    options = ["--seed", str(seed)]
    if firmware is not None:
        options += ["--sitl", str(firmware)]
    if victim is not None:
        options += ["--kill-agent", f"{victim}@{kill_at:g}"]
    return fly_and_measure(config, directory / f"{vehicles}_{config.stem}_{victim_name}",
                           options, lambda recording: measure(recording, victim),
                           {"vehicles": vehicles, "config": config.stem, "victim": victim_name})


def _num(value: object, spec: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return format(value, spec)


def print_table(results: list[dict[str, object]], console: Console) -> None:
    table = Table(title="losing one drone (kill -9 of its agent)")
    for column in ("vehicles", "config", "lost", "at [s]", "min λ̄ − ε after (per target)",
                   "below ε − tol [s]", "first below / said [s]", "breaches said", "verdict",
                   "min dist [m]", "final err [m]"):
        table.add_column(column)
    for r in results:
        if "failed" in r:
            table.add_row(str(r["vehicles"]), str(r["config"]), str(r["victim"]), "",
                          f"did not fly (exit {r['exit_code']}): {r['failed']}")
            continue
        margins = " ".join(f"{m:+.4f}" for m in r["min_margin_per_target"])
        table.add_row(
            str(r["vehicles"]), str(r["config"]), str(r["victim"]), _num(r["loss_s"], ".2f"),
            margins, _num(r["below_s"], ".2f"),
            f"{_num(r['first_below_s'], '.2f')} / {_num(r['first_said_s'], '.2f')}",
            str(r["breaches_said"]), "OK" if r["ok"] else "; ".join(r["violations"])[:50],
            _num(r["min_distance_m"], ".2f"), _num(r["final_error_m"], ".3f"))
    console.print(table)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", nargs="+", default=["emulator", "ardupilot"],
                        choices=("emulator", "ardupilot", "px4"))
    parser.add_argument("--case", nargs="+", default=["case1", "case2"])
    parser.add_argument("--drones", nargs="+", type=int, default=[3, 6])
    parser.add_argument("--victims", nargs="+", type=int, default=None,
                        help="only these drones (default: each drone in turn)")
    parser.add_argument("--kill-at", type=float, default=12.0, metavar="S")
    parser.add_argument("--duration", type=float, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--baseline", action="store_true", help="also a run without a loss")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--keep", type=Path, default=None,
                        help="keep recordings and logs here (default: a temporary directory)")
    args = parser.parse_args(argv)
    console = Console(width=180)
    builds: dict[str, Path | None] = {"emulator": None}
    for vehicles in args.vehicles:
        if vehicles == "emulator":
            continue
        firmware = find_firmware(vehicles)
        if firmware is None:
            console.print(f"drone_loss: no {vehicles} SITL build (../shared/autopilots/ or "
                          f"$VIGIL_{'ARDUCOPTER' if vehicles == 'ardupilot' else 'PX4'})")
            return 2
        builds[vehicles] = firmware.path
    results: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory(prefix="vigil-loss-") as scratch:
        directory = args.keep or Path(scratch)
        directory.mkdir(parents=True, exist_ok=True)
        for vehicles in args.vehicles:
            for case in args.case:
                for n in args.drones:
                    config = write_config(case, n, args.duration, directory)
                    victims = [v for v in (args.victims or range(n)) if v < n]
                    for victim in ([None] if args.baseline else []) + victims:
                        result = run_mission(config, vehicles, builds[vehicles], victim,
                                             args.kill_at, args.seed, directory)
                        results.append(result)
                        console.print(
                            f"{vehicles} {config.stem} lost {result['victim']}: "
                            + ("did not fly" if "failed" in result else
                               f"min λ̄ − ε {result['min_margin']:+.4f}, said "
                               f"{result['breaches_said']}")
                            + f" ({result['wall_s']} s)", highlight=False)
                        if args.json is not None:
                            args.json.write_text(json.dumps(results, indent=1))
    print_table(results, console)
    return 0 if all("failed" not in r for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
