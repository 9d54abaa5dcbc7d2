"""The simulator's exceptions: one root, each one naming what was wrong and what was expected.

A bad configuration is a :class:`~companion.table.ConfigError` (a ``ValueError``), the error of
the one table reader every configuration file goes through (the companion's too, which is why
it is not a :class:`SimError`); it is re-exported here."""

from __future__ import annotations

from companion.table import ConfigError

__all__ = ["ConfigError", "SimError", "SimStateError"]


class SimError(Exception):
    """Root of every error raised by ``sitl_sim`` but a bad configuration (:class:`ConfigError`)."""


class SimStateError(SimError, RuntimeError):
    """The simulation was used out of order (stepped before reset, stepped after it ended)."""
