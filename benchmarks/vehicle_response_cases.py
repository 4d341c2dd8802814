"""The thesis cases with the vehicles' velocity response: ideal (the thesis) against the lag and
acceleration limit fitted to ArduCopter SITL (``swarm.models.kinematics.ARDUCOPTER_SITL_RESPONSE``,
``[vehicles] response = "arducopter"``), side by side, in-process (the reference simulator; a
lockstep process swarm gives the same numbers bit for bit).

    python benchmarks/vehicle_response_cases.py [--cases case1 case2 case3] [--seeds 0 1 2]

Prints, per case, response and seed: the smallest λ̄ − ε after control start and how long
λ̄ < ε, the smallest pairwise distance against Δ, the largest |u|, QP fallbacks, the final
estimation error, and which SPEC invariants failed (with the case's tolerances).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from common import CONFIGS
from rich.console import Console
from rich.table import Table

from swarm.runs.checks import check_invariants, min_pairwise_distance, nanmin, start_index
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config


def run_case(case: str, response: str, seed: int) -> dict[str, object]:
    config = load_config(CONFIGS / f"{case}.toml")
    config = dataclasses.replace(config, vehicles=dataclasses.replace(config.vehicles,
                                                                      response=response))
    started = time.perf_counter()
    record = run_reference(config, seed)
    k0 = start_index(record)
    eps = config.gramian.epsilon
    below = (record.lambda_bar[k0:] < eps).any(axis=1).any(axis=1)
    violations = check_invariants(record)
    return {
        "case": case, "response": response, "seed": seed,
        "min_margin": float(nanmin(record.lambda_bar[k0:] - eps)),
        "time_below_s": float(below.sum() * config.scenario.dt_s),
        "min_distance_m": min_pairwise_distance(record),
        "delta_m": config.control.collision_distance_m,
        "max_u_m_s": float(np.abs(record.velocities_m_s).max()),
        "fallbacks": int(record.qp_fallback.sum()),
        "final_error_m": float(record.position_errors()[-1].max()),
        "violations": sorted({v.invariant for v in violations}),
        "tolerance": config.checks.lambda_tolerance,
        "wall_s": time.perf_counter() - started,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["case1", "case2", "case3"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    args = parser.parse_args()
    table = Table(title="thesis cases: ideal vehicles vs the ArduCopter SITL response")
    for column in ("case", "response", "seed", "min λ̄−ε", "tol", "λ̄<ε [s]", "min dist [m]",
                   "max |u| [m/s]", "fallbacks", "final err [m]", "verdict"):
        table.add_column(column, justify="right")
    for case in args.cases:
        for seed in args.seeds:
            for response in ("ideal", "arducopter"):
                r = run_case(case, response, seed)
                verdict = "OK" if not r["violations"] else "FAILED " + ",".join(
                    r["violations"])  # type: ignore[arg-type]
                table.add_row(case, response, str(seed), f"{r['min_margin']:+.4f}",
                              f"{r['tolerance']:g}", f"{r['time_below_s']:.2f}",
                              f"{r['min_distance_m']:.3f}", f"{r['max_u_m_s']:.3f}",
                              str(r["fallbacks"]), f"{r['final_error_m']:.4f}", verdict)
    Console(width=160).print(table)


if __name__ == "__main__":
    main()
