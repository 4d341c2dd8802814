"""A failed local QP on disk: an agent saves the first few its drone meets, anyone can load one
and solve it again, away from the swarm.

``save_failed_qp(failed, path)`` writes one ``FailedQp`` (``swarm.core.qp``) as an ``.npz``:
the QP's arrays (P, q, A, lower, z_min, z_max) and what the solver answered.
``load_failed_qp(path)`` reads it back; a file that is not one says so in one line
(``FailedQpFileError``).

    python -m swarm.runs.failed_qp LOGS/qp-drone2-step41-hard.npz

prints what failed and solves the QP again with the swarm's solver settings (``QpSolver``).
"""

from __future__ import annotations

import json
import sys
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from swarm.core.qp import FailedQp, LocalQp, QpSolver
from swarm.errors import EXIT_OK, EXIT_USAGE, UsageError, run_main

PROG = "failed_qp"
FORMAT = "vigil-failed-qp/1"
_ARRAYS = ("cost_hessian", "cost_linear", "rows", "lower", "z_min", "z_max")


class FailedQpFileError(UsageError, ValueError):
    """A file that is not a readable failed-QP dump."""


def dump_name(failed: FailedQp) -> str:
    """The file name an agent gives ``failed``: ``qp-drone2-step41-hard.npz``."""
    attempt = failed.attempt.replace(", ", "-").replace(" ", "-")
    return f"qp-drone{failed.drone_id}-step{failed.step}-{attempt}.npz"


def save_failed_qp(failed: FailedQp, path: Path) -> Path:
    """Write ``failed`` to ``path`` (an ``.npz``); returns the path."""
    meta = {"format": FORMAT, "drone_id": failed.drone_id, "step": failed.step,
            "attempt": failed.attempt, "status": failed.status,
            "iterations": failed.iterations, "max_violation": repr(failed.max_violation)}
    arrays = {name: getattr(failed.qp, name) for name in _ARRAYS}
    with path.open("wb") as out:
        np.savez(out, meta=np.array(json.dumps(meta)), **arrays)
    return path


def load_failed_qp(path: Path) -> FailedQp:
    """The ``FailedQp`` in ``path``; ``FailedQpFileError`` naming the file if it is not one."""
    failed: FailedQp | None = None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("format") == FORMAT:
                qp = LocalQp(*(np.array(data[name], dtype=float) for name in _ARRAYS))
                failed = FailedQp(int(meta["drone_id"]), int(meta["step"]),
                                  str(meta["attempt"]), qp, str(meta["status"]),
                                  int(meta["iterations"]), float(meta["max_violation"]))
    except (OSError, KeyError, TypeError, ValueError, zipfile.BadZipFile) as err:
        raise FailedQpFileError(f"{path}: not a readable failed-QP dump ({err})") from err
    if failed is None:
        raise FailedQpFileError(f"{path}: not a failed-QP dump (format "
                                f"{meta.get('format')!r}, expected {FORMAT!r})")
    qp = failed.qp
    n, rows = qp.cost_linear.shape[0], qp.rows.shape
    if qp.cost_hessian.shape != (n, n) or rows[1:] != (n,) or qp.lower.shape != rows[:1] \
            or qp.z_min.shape != (n,) or qp.z_max.shape != (n,):
        raise FailedQpFileError(f"{path}: a failed-QP dump with inconsistent shapes (P "
                                f"{qp.cost_hessian.shape}, A {rows}, {n} variables)")
    return failed


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1 or args[0].startswith("-"):
        print("usage: python -m swarm.runs.failed_qp FILE.npz  (a QP an agent saved when it "
              "failed: solve it again)", file=sys.stderr)
        return EXIT_USAGE
    return run_main(PROG, lambda: _solve_again(Path(args[0])))


def _solve_again(path: Path) -> int:
    failed = load_failed_qp(path)
    print(failed.describe())
    again = QpSolver().solve(failed.qp)
    print(f"solved again: {again.status} after {again.iterations} iterations, max violation "
          f"{again.max_violation:.3g}, accepted: {again.found}, z = {again.z.tolist()}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
