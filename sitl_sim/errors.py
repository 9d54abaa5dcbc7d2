"""The simulator's exceptions: one root, each one naming what was wrong and what was expected."""

from __future__ import annotations

__all__ = ["ConfigError", "SimError", "SimStateError"]


class SimError(Exception):
    """Root of every error raised by ``sitl_sim``."""


class ConfigError(SimError, ValueError):
    """A configuration file or value is missing, malformed or out of range.

    The message names the file (when there is one), the field and what was expected.
    """


class SimStateError(SimError, RuntimeError):
    """The simulation was used out of order (stepped before reset, stepped after it ended)."""
