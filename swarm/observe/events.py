"""What counts as trouble in a drone's telemetry: the counters whose rise is worth a line.

``WARNED_COUNTERS`` (name, label) and ``URGENT_COUNTERS``, and ``increased_counters(before,
now)``: the dashboard's warning lines and the scene's Foxglove log both come from here.
"""

from __future__ import annotations

from swarm.messages.wire import TelemetryCounters

# Counters that raise a warning line when they go up, with how the line names them.
WARNED_COUNTERS: tuple[tuple[str, str], ...] = (
    ("late_steps", "late steps"),
    ("stale_neighbour_messages", "stale neighbour messages"),
    ("qp_fallbacks", "QP fallbacks"),
    ("rejected_messages", "rejected messages"),
    ("vehicle_events", "vehicle events (not asked for)"),
    ("rate_limit_releases", "rate-box releases"),
    ("reference_resets", "reference resets"),
    ("lambda_breaches", "targets its λ̄ copy let fall below ε − tol"),
    ("safety_conflicts", "steps the safety envelope overruled localization"),
    ("link_conflicts", "steps a keep row of the radio overruled localization"),
    ("splits_said", "times its radio found the swarm split (docs/network.md)"),
)
# Of those, the ones whose every increase is printed at once (not held back by
# ``warning_period_s``): a drone saying it cannot hold a target, its vehicle not as asked,
# the swarm split.
URGENT_COUNTERS: frozenset[str] = frozenset({"lambda_breaches", "vehicle_events",
                                             "splits_said"})
URGENT_LABELS = frozenset(label for name, label in WARNED_COUNTERS if name in URGENT_COUNTERS)


def increased_counters(reported: TelemetryCounters | None,
                       now: TelemetryCounters) -> list[tuple[str, int, int]]:
    """(label, increase, total) of every warned counter that went up since ``reported``."""
    out = []
    for name, label in WARNED_COUNTERS:
        total = getattr(now, name)
        before = 0 if reported is None else getattr(reported, name)
        if total > before:
            out.append((label, total - before, total))
    return out
