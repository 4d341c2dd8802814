"""The root of every error the project raises on purpose.

Each module keeps its own error class (``ConfigError``, ``WireError``, ``LinkError``, ...) next
to the code that raises it, also deriving from the built-in exception it stood for before
(``ValueError``, ``RuntimeError``), so ``except VigilError`` catches anything of ours and
nothing else: a ``VigilError`` is a refusal or a failure we expected and worded; anything else
reaching a command line is a bug.
"""

from __future__ import annotations


class VigilError(Exception):
    """An error raised on purpose by Vigil (swarm, sim_world), with a message for a user."""
