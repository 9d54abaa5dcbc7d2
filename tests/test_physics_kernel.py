"""The physics kernel: compiled (numba) and Python give the same floats, the same flights as
every flight recorded before the kernel existed, and a whole control period in one call is the
same as one call per physics step."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from companion.contract import Command
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.physics import kernel
from sitl_sim.scenario import InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.world import episode_world
from training.provenance import REPO

# Digests of the ground truth of three cascade-flown episodes (seed 7) per world, recorded with
# the pure-Python physics before the kernel (commit 482bd7b): the kernel changes no float.
RECORDED = {
    "configs/scenario.toml": "729fafa7e94aca31",
    "configs/scenario_wind.toml": "321bd6f2999f8563",
    "configs/sites/slope.toml": "0a4ae64a132dd6a1",
}

_DIGEST = """
import hashlib, json, sys
import numpy as np
from expert.cascade import CascadeLander
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.physics import kernel
from sitl_sim.scenario import InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.world import episode_world

out = {"kernel": kernel.KERNEL}
vehicle, sim_cfg = load_vehicle(), load_sim()
for path in sys.argv[1:]:
    scenario = load_scenario(path)
    cfg = sim_cfg.with_planet(scenario.world) if scenario.world != sim_cfg.planet else sim_cfg
    sim, pilot = Simulator(vehicle, cfg, render=False), CascadeLander(vehicle, cfg.planet)
    h = hashlib.sha256()
    for ep in range(3):
        sim.reset(InitialStateSampler(scenario, 7).sample(ep), 7, episode_world(scenario, 7, ep))
        for _ in range(600):
            gt = sim.ground_truth()
            h.update(np.asarray(gt.pos_ned_m).tobytes())
            h.update(np.asarray(gt.quat_wxyz).tobytes())
            ev = sim.step(pilot.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz))
            if ev is not None:
                h.update(repr((ev.time_s, ev.pos_ned_m.tolist(), ev.vel_ned_m_s.tolist(),
                               ev.tilt_rad)).encode())
    out[path] = h.hexdigest()[:16]
print(json.dumps(out))
"""


def _digests(kernel_name: str) -> dict[str, str]:
    env = {**os.environ, "VISLAND_PHYSICS_KERNEL": kernel_name}
    proc = subprocess.run(
        [sys.executable, "-c", _DIGEST, *RECORDED],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    import json

    return json.loads(proc.stdout)


@pytest.mark.parametrize("name", ["numba", "python"])
def test_both_kernels_fly_the_flights_recorded_before_the_kernel(name):
    got = _digests(name)
    assert got.pop("kernel") == name  # the dev install has numba: the compiled one really ran
    assert got == RECORDED


def test_a_control_period_in_one_call_equals_one_call_per_physics_step():
    """Simulator.step's one-call period and step_physics' loop: the same state, touchdown and
    rate-loop state, through a flight that comes down onto the ground and rests there."""
    vehicle, sim_cfg = load_vehicle(), load_sim()
    scenario = load_scenario(None)
    initial = InitialStateSampler(scenario, 3).sample(0)
    sims = [Simulator(vehicle, sim_cfg, render=False) for _ in range(2)]
    for sim in sims:
        sim.reset(initial, 3, episode_world(scenario, 3, 0))
    rng = np.random.default_rng(0)
    events = []
    for k in range(400):
        # a descent that reaches the ground (low thrust), wobbling rates, disarmed at the end
        thrust = 0.2 if k < 300 else 0.6
        cmd = Command(thrust, rng.normal(size=3) * 0.3) if k < 380 else None
        whole = sims[0].step(cmd)
        steps = [sims[1].step_physics(cmd) for _ in range(sim_cfg.substeps)]
        stepwise = next((e for e in steps if e is not None), None)
        assert sims[0]._x == sims[1]._x
        assert sims[0].rate_controller.state == sims[1].rate_controller.state
        assert (whole is None) == (stepwise is None)
        if whole is not None:
            events.append(whole)
            assert whole.time_s == stepwise.time_s
            assert whole.pos_ned_m.tolist() == stepwise.pos_ned_m.tolist()
            assert whole.vel_ned_m_s.tolist() == stepwise.vel_ned_m_s.tolist()
            assert whole.tilt_rad == stepwise.tilt_rad
    assert events, "the flight never touched down: the test flew nothing it checks"
    assert sims[0].contact is not None and sims[0].contact.time_s == events[0].time_s


def test_the_kernel_is_refused_by_a_bad_choice():
    env = {**os.environ, "VISLAND_PHYSICS_KERNEL": "fortran"}
    proc = subprocess.run(
        [sys.executable, "-c", "import sitl_sim.physics.kernel"],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode != 0
    assert "VISLAND_PHYSICS_KERNEL: expected 'numba' or 'python', got 'fortran'" in proc.stderr


def test_the_compiled_kernel_is_the_python_one_on_random_states():
    """Every kernel entry point, compiled against its own Python source (``py_func``), on
    random states, commands and winds: the same floats, bit for bit."""
    if kernel.KERNEL != "numba":
        pytest.skip("numba is not installed: only the Python kernel runs")
    vehicle, sim_cfg = load_vehicle(), load_sim()
    sim = Simulator(vehicle, sim_cfg, render=False)
    pc, rc = sim.phys.constants, sim.rate_controller.constants
    rng = np.random.default_rng(1)
    for i in range(300):
        x = rng.normal(size=17)
        x[6:10] /= np.linalg.norm(x[6:10])
        x[13:17] = np.abs(x[13:17]) * 3.0
        x[2] = -abs(x[2]) * 0.01  # just above the ground: some steps touch down
        x = tuple(x.tolist())
        rs = (*rng.normal(size=6).tolist(), float(i % 2), 0.0)
        sp = tuple((rng.normal(size=3) * (4.0 if i % 3 else 0.3)).tolist())
        wind = tuple((rng.normal(size=3) * 5.0).tolist())
        collective = float(rng.uniform(0.0, 1.0)) * sim.phys.max_total_thrust_n
        args = (pc, rc, x, rs, bool(i % 5), *sp, collective, 0.004, 3, *wind, bool(i % 4))
        assert kernel.period(*args) == _python(kernel.period)(*args)
        rl = (rc, rs, *sp, collective, *x[10:13], 0.004)
        assert kernel.rate_loop(*rl) == _python(kernel.rate_loop)(*rl)


def _python(fn):
    """``fn`` run as Python all the way down: its source and every kernel function it calls."""
    names = {n: getattr(kernel, n) for n in dir(kernel) if hasattr(getattr(kernel, n), "py_func")}

    def run(*args):
        try:
            for n, f in names.items():
                setattr(kernel, n, f.py_func)
            return fn.py_func(*args)
        finally:
            for n, f in names.items():
                setattr(kernel, n, f)

    return run
