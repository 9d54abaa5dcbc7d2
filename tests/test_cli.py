"""CLI smoke tests on tiny budgets: the commands a user types, as separate processes."""

from __future__ import annotations

import json

import pytest
from helpers import visland


def test_bench_sim_prints_a_real_time_factor():
    proc = visland("bench", "sim", "--seconds", "2", "--repeats", "1", "--json")
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res["realtime_factor"] > 1.0
    assert res["realtime_factor_physics_only"] > res["realtime_factor"]
    assert res["kernel"] == "numba"  # the sim extra installs it: the compiled physics ran
    # one control period per call is the cheaper path (the SITL's one step per call is timed too)
    assert res["physics_step_us"] < res["physics_step_us_stepwise"]


@pytest.mark.parametrize(
    "args", [["--help"], ["demo", "--help"], ["bench", "--help"], ["sitl", "--help"]]
)
def test_help(args):
    proc = visland(*args)
    assert proc.returncode == 0 and "usage: visland" in proc.stdout
