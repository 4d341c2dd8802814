"""CPU per simulated step against the swarm size N, from a lockstep section (issue 16).

    python benchmarks/plot_scaling.py [LOCKSTEP_JSON] [--out PNG]

(``run_all.py`` draws it after its lockstep section, next to ``lockstep.json``.) One panel:
the world process, the median agent (all its threads) and the agent's Zenoh receive path,
in CPU milliseconds per simulated step, each point the median over the section's runs with
its min-max as an error bar; the dashed lines continue each curve's N = first value
linearly (per drone for the world, flat for an agent), so growth faster than that shows as a
gap, and the dotted line is issue 16's bound for the world (0.3 ms per drone). A section of
one N draws its points alone.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import matplotlib
from common import RESULTS

matplotlib.use("Agg")
import matplotlib.pyplot as plt

WORLD_TARGET_MS_PER_DRONE = 0.3  # issue 16: world CPU per step ≤ 0.3 ms per drone up to N = 48

# (summary key, label, how its design line grows with N: "per_drone" or "flat")
CURVES = (
    ("world_cpu_ms_per_step", "world process", "per_drone"),
    ("agent_cpu_ms_per_step", "median agent, every thread", "flat"),
    ("agent_zenoh_rx_ms_per_step", "median agent, Zenoh receive + callbacks", "flat"),
)


def scaling_points(lockstep: dict[str, Any]) -> dict[str, list[tuple[int, float, float, float]]]:
    """Per curve: (N, median, min, max) of each swarm size that has the figure."""
    points: dict[str, list[tuple[int, float, float, float]]] = {}
    for key, _label, _growth in CURVES:
        rows = []
        for result in sorted(lockstep["results"], key=lambda r: r["n_drones"]):
            figure = result["summary"].get(key)
            if figure is None or figure.get("median") is None:
                continue
            rows.append((int(result["n_drones"]), float(figure["median"]),
                         float(figure["min"]), float(figure["max"])))
        points[key] = rows
    return points


def write_scaling_plot(lockstep: dict[str, Any], path: Path) -> Path:
    """Draw the plot of a lockstep section's result into ``path`` (PNG)."""
    points = scaling_points(lockstep)
    fig, ax = plt.subplots(figsize=(7.0, 4.5), dpi=120)
    for key, label, growth in CURVES:
        rows = points[key]
        if not rows:
            continue
        n = [r[0] for r in rows]
        median = [r[1] for r in rows]
        errors = [[r[1] - r[2] for r in rows], [r[3] - r[1] for r in rows]]
        line = ax.errorbar(n, median, yerr=errors, marker="o", capsize=3, label=label)
        first_n, first = rows[0][0], rows[0][1]
        design = [first * (x / first_n) if growth == "per_drone" else first for x in n]
        ax.plot(n, design, linestyle="--", color=line[0].get_color(), alpha=0.6)
    sizes = sorted({r["n_drones"] for r in lockstep["results"]})
    ax.plot(sizes, [WORLD_TARGET_MS_PER_DRONE * n for n in sizes], linestyle=":", color="k",
            label=f"target for the world: {WORLD_TARGET_MS_PER_DRONE:g} ms per drone")
    ax.set_xticks(sizes)
    ax.set_xlabel("drones N (lockstep, Case 2 scaled at its density)")
    ax.set_ylabel("CPU per simulated step [ms]")
    ax.set_title("Cost against swarm size (dashed: linear for the world, flat per agent)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("lockstep", nargs="?", type=Path, default=RESULTS / "lockstep.json")
    parser.add_argument("--out", type=Path, default=None,
                        help="PNG to write (default: scaling.png next to the JSON)")
    args = parser.parse_args(argv)
    result = json.loads(args.lockstep.read_text())
    out = args.out or args.lockstep.with_name("scaling.png")
    print(f"wrote {write_scaling_plot(result, out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
