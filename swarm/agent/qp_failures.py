"""What an agent does with a QP its core could not solve: log the first few, each saved as a
file a developer can solve again (``swarm.runs.failed_qp``), and count the rest."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from swarm.core.qp import FailedQp
from swarm.runs.failed_qp import dump_name, save_failed_qp

QP_FAILURES_LOGGED = 5  # the first failed QPs are logged (and saved); later ones are counted


class QpFailureLog:
    """Counts failed QPs; logs the first ``limit``, each saved in ``dump_dir`` if given."""

    def __init__(self, log: Callable[[str], None], dump_dir: Path | None,
                 limit: int = QP_FAILURES_LOGGED) -> None:
        self.log, self.dump_dir, self.limit = log, dump_dir, limit
        self.count = 0
        self.saved: list[Path] = []

    def report(self, failed: FailedQp) -> None:
        self.count += 1
        if self.count > self.limit:
            return
        where = ""
        if self.dump_dir is not None:
            try:
                path = save_failed_qp(failed, self.dump_dir / dump_name(failed))
            except OSError as err:
                where = f"; not saved ({err})"
            else:
                self.saved.append(path)
                where = f"; saved to {path}"
        later = "; later ones are counted only" if self.count == self.limit else ""
        self.log(f"{failed.describe()}{where}{later}")
