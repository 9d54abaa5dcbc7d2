"""Transitional: the SITL moved to :mod:`sitl_sim.mavlink` (removed once every caller uses it)."""

import sys

from sitl_sim.mavlink.sitl import MavlinkSitl, main, run_sitl

__all__ = ["MavlinkSitl", "main", "run_sitl"]

if __name__ == "__main__":
    sys.exit(main())
