"""The physics kernel: the rate loop, the rotors and the rigid body over one or more physics steps.

One source for the equations of :mod:`sitl_sim.physics.dynamics` (the state derivative and its
RK4 step) and of :mod:`sitl_sim.physics.rate_controller` (PID + mixer), written on plain floats
and tuples so that the same functions run two ways:

* compiled by numba (``pip install 'visland[sim]'`` installs it) — the default when it imports;
* as plain Python — when numba is absent, or with ``VISLAND_PHYSICS_KERNEL=python``.

Both give the same floats bit for bit (``tests/test_dynamics.py`` holds them to it): numba
compiles without ``fastmath``, so LLVM neither reorders nor fuses (no FMA contraction) the
operations, and the math functions are the C library's in both. :data:`KERNEL` names the one in use
(``visland bench sim --json`` reports it).

:func:`period` is the unit of work: ``n`` physics steps of the rate loop and RK4 holding one
command and one wind, with the flat ground's contact resolved in the kernel (``flat``) or left to
the caller (a site's surfaces, :mod:`sitl_sim.site.contact`). The simulator asks for a whole
control period at once where nothing outside the kernel changes between steps (no wind, no site,
no camera latency), else for one step at a time — the SITL, whose setpoints arrive between steps,
always steps one at a time.

Tuples (all floats, so numba sees homogeneous tuples):

* plant constants ``pc`` (:func:`plant_constants`): ``1/m, g, k_m, Ixx, Iyy, Izz, Iyy-Izz,
  Izz-Ixx, Ixx-Iyy, rx0..3, ry0..3, kdrag x/y/z, 1/tau, lag (1.0 or 0.0), 2.0``. The last is
  the exponent of the squares in the quaternion's norm and the resting yaw: the C library's
  ``pow(x, 2.0)``, as CPython's ``x ** 2`` computed them before this kernel existed, is not
  always ``x * x`` (glibc's pow is within 0.52 ULP, not correctly rounded), and LLVM folds a
  constant exponent into ``x * x``; an exponent read at run time keeps every flight recorded
  before the kernel identical, bit for bit;
* rate-loop constants ``rc`` (:func:`rate_constants`): ``kp0..2, ki0..2, kd0..2, integrator
  limits 0..2, max rates 0..2, Ixx, Iyy, Izz, Izz-Iyy, Ixx-Izz, Iyy-Ixx, T_max total, T_max rotor,
  the inverse allocation's roll/pitch/yaw columns (4 each)``;
* rate-loop state ``rs``: ``integral 0..2, previous error 0..2, has previous (1.0/0.0),
  saturated (1.0/0.0)``.
"""

from __future__ import annotations

import math
import os

__all__ = [
    "KERNEL",
    "RATE_RESET",
    "flat_contact",
    "integrate",
    "period",
    "plant_constants",
    "rate_constants",
    "rate_loop",
    "rates",
    "rk4",
]


def _compiler():
    """numba's ``njit`` (cached on disk, no fastmath) or None: the kernel runs as Python."""
    choice = os.environ.get("VISLAND_PHYSICS_KERNEL", "numba").strip().lower()
    if choice not in ("numba", "python"):
        raise ValueError(f"VISLAND_PHYSICS_KERNEL: expected 'numba' or 'python', got {choice!r}")
    if choice == "python":
        return None
    try:
        import numba
    except ImportError:
        return None
    return numba.njit(cache=True, fastmath=False, nogil=True)


_JIT = _compiler()
KERNEL = "python" if _JIT is None else "numba"
"""Which kernel runs: ``numba`` (compiled) or ``python``."""


def _kernel(fn):
    return fn if _JIT is None else _JIT(fn)


RATE_RESET = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
"""The rate loop's state after a reset: no integral, no previous error, not saturated."""


def plant_constants(phys) -> tuple[float, ...]:
    """``pc`` for a :class:`sitl_sim.physics.dynamics.Physics` (its vehicle on its planet)."""
    lag = phys.tau_motor > 0.0
    return (
        1.0 / phys.mass, phys.g, phys.km, phys.ixx, phys.iyy, phys.izz,
        phys.iyy - phys.izz, phys.izz - phys.ixx, phys.ixx - phys.iyy,
        *phys.rx, *phys.ry, *phys.kdrag,
        1.0 / phys.tau_motor if lag else 0.0, 1.0 if lag else 0.0,
        2.0,
    )  # fmt: skip


def rate_constants(gains, phys) -> tuple[float, ...]:
    """``rc`` for rate-loop gains (:class:`sitl_sim.config.RateControllerConfig`) on ``phys``."""
    inv = phys.allocation_inv
    return tuple(
        float(v)
        for v in (
            *gains.kp, *gains.ki, *gains.kd, *gains.integrator_limit_rad_s2,
            *gains.max_rate_rad_s, phys.ixx, phys.iyy, phys.izz,
            phys.izz - phys.iyy, phys.ixx - phys.izz, phys.iyy - phys.ixx,
            phys.max_total_thrust_n, phys.max_rotor_thrust,
            *inv[:, 1], *inv[:, 2], *inv[:, 3],
        )
    )  # fmt: skip


# --------------------------------------------------------------------------- rigid body


@_kernel
def rates(pc, vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4, c1, c2, c3, c4, wn, we, wd):
    """The state derivative but for the position rows (which are the velocity): the equations of
    :mod:`sitl_sim.physics.dynamics`. Drag acts on the air-relative velocity ``v - wind``; still
    air is a zero wind (``v - 0.0`` is ``v`` for every float, signed zeros included)."""
    inv_m, g, km = pc[0], pc[1], pc[2]
    ixx, iyy, izz, i_p, i_q, i_r = pc[3], pc[4], pc[5], pc[6], pc[7], pc[8]
    rx0, rx1, rx2, rx3 = pc[9], pc[10], pc[11], pc[12]
    ry0, ry1, ry2, ry3 = pc[13], pc[14], pc[15], pc[16]
    kx, ky, kz, inv_tau = pc[17], pc[18], pc[19], pc[20]
    vn, ve, vd = vn - wn, ve - we, vd - wd
    # translation: rotation body -> NED, drag on the air-relative body velocity
    r00 = 1 - 2 * (qy * qy + qz * qz)
    r01 = 2 * (qx * qy - qw * qz)
    r02 = 2 * (qx * qz + qw * qy)
    r10 = 2 * (qx * qy + qw * qz)
    r11 = 1 - 2 * (qx * qx + qz * qz)
    r12 = 2 * (qy * qz - qw * qx)
    r20 = 2 * (qx * qz - qw * qy)
    r21 = 2 * (qy * qz + qw * qx)
    r22 = 1 - 2 * (qx * qx + qy * qy)
    vbx = r00 * vn + r10 * ve + r20 * vd
    vby = r01 * vn + r11 * ve + r21 * vd
    vbz = r02 * vn + r12 * ve + r22 * vd
    fbx = -kx * abs(vbx) * vbx
    fby = -ky * abs(vby) * vby
    fbz = -kz * abs(vbz) * vbz - (t1 + t2 + t3 + t4)
    # Euler: J w' = tau - w x (J w), J diagonal; q' = 1/2 q (x) (0, w); the rotor lag
    if pc[21] > 0.0:
        dt1, dt2 = (c1 - t1) * inv_tau, (c2 - t2) * inv_tau
        dt3, dt4 = (c3 - t3) * inv_tau, (c4 - t4) * inv_tau
    else:
        dt1 = dt2 = dt3 = dt4 = 0.0
    return (
        (r00 * fbx + r01 * fby + r02 * fbz) * inv_m,
        (r10 * fbx + r11 * fby + r12 * fbz) * inv_m,
        (r20 * fbx + r21 * fby + r22 * fbz) * inv_m + g,
        0.5 * (-qx * p - qy * q - qz * r),
        0.5 * (qw * p + qy * r - qz * q),
        0.5 * (qw * q - qx * r + qz * p),
        0.5 * (qw * r + qx * q - qy * p),
        (-(ry0 * t1 + ry1 * t2 + ry2 * t3 + ry3 * t4) + i_p * q * r) / ixx,
        (rx0 * t1 + rx1 * t2 + rx2 * t3 + rx3 * t4 + i_q * r * p) / iyy,
        (km * (t1 + t2 - t3 - t4) + i_r * p * q) / izz,
        dt1,
        dt2,
        dt3,
        dt4,
    )


@_kernel
def _rates_at(pc, x, h, k, c1, c2, c3, c4, wn, we, wd):
    """:func:`rates` at the stage ``x + h k`` (the position rows do not enter it)."""
    _, _, _, vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4 = x
    return rates(
        pc, vn + h * k[0], ve + h * k[1], vd + h * k[2], qw + h * k[3], qx + h * k[4],
        qy + h * k[5], qz + h * k[6], p + h * k[7], q + h * k[8], r + h * k[9], t1 + h * k[10],
        t2 + h * k[11], t3 + h * k[12], t4 + h * k[13], c1, c2, c3, c4, wn, we, wd,
    )  # fmt: skip


@_kernel
def rk4(pc, x, c1, c2, c3, c4, dt, wn, we, wd):
    """One classic RK4 step of :func:`rates` (no ground, no renormalisation); the commanded rotor
    thrusts and the wind are held over the step (zero-order hold)."""
    pn, pe, pd, vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4 = x
    h = 0.5 * dt
    # k1 at x; k2 at x + h k1; k3 at x + h k2; k4 at x + dt k3 (the position rows' k is the
    # stage's velocity)
    e = rates(pc, vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4, c1, c2, c3, c4, wn, we, wd)
    b = _rates_at(pc, x, h, e, c1, c2, c3, c4, wn, we, wd)
    c = _rates_at(pc, x, h, b, c1, c2, c3, c4, wn, we, wd)
    d = _rates_at(pc, x, dt, c, c1, c2, c3, c4, wn, we, wd)
    vn2, ve2, vd2 = vn + h * e[0], ve + h * e[1], vd + h * e[2]
    vn3, ve3, vd3 = vn + h * b[0], ve + h * b[1], vd + h * b[2]
    vn4, ve4, vd4 = vn + dt * c[0], ve + dt * c[1], vd + dt * c[2]
    s = dt / 6.0  # x + dt/6 (k1 + 2 k2 + 2 k3 + k4), row by row
    return (
        pn + s * (vn + 2.0 * vn2 + 2.0 * vn3 + vn4),
        pe + s * (ve + 2.0 * ve2 + 2.0 * ve3 + ve4),
        pd + s * (vd + 2.0 * vd2 + 2.0 * vd3 + vd4),
        vn + s * (e[0] + 2.0 * b[0] + 2.0 * c[0] + d[0]),
        ve + s * (e[1] + 2.0 * b[1] + 2.0 * c[1] + d[1]),
        vd + s * (e[2] + 2.0 * b[2] + 2.0 * c[2] + d[2]),
        qw + s * (e[3] + 2.0 * b[3] + 2.0 * c[3] + d[3]),
        qx + s * (e[4] + 2.0 * b[4] + 2.0 * c[4] + d[4]),
        qy + s * (e[5] + 2.0 * b[5] + 2.0 * c[5] + d[5]),
        qz + s * (e[6] + 2.0 * b[6] + 2.0 * c[6] + d[6]),
        p + s * (e[7] + 2.0 * b[7] + 2.0 * c[7] + d[7]),
        q + s * (e[8] + 2.0 * b[8] + 2.0 * c[8] + d[8]),
        r + s * (e[9] + 2.0 * b[9] + 2.0 * c[9] + d[9]),
        t1 + s * (e[10] + 2.0 * b[10] + 2.0 * c[10] + d[10]),
        t2 + s * (e[11] + 2.0 * b[11] + 2.0 * c[11] + d[11]),
        t3 + s * (e[12] + 2.0 * b[12] + 2.0 * c[12] + d[12]),
        t4 + s * (e[13] + 2.0 * b[13] + 2.0 * c[13] + d[13]),
    )


@_kernel
def integrate(pc, x, c1, c2, c3, c4, dt, wn, we, wd):
    """:func:`rk4` and the quaternion renormalised: the free flight of one step, no ground."""
    pn, pe, pd, vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4 = rk4(
        pc, x, c1, c2, c3, c4, dt, wn, we, wd
    )
    two = pc[22]  # see plant_constants: squares as CPython's ``x ** 2`` computes them
    n = math.sqrt(math.pow(qw, two) + math.pow(qx, two) + math.pow(qy, two) + math.pow(qz, two))
    return (pn, pe, pd, vn, ve, vd, qw / n, qx / n, qy / n, qz / n, p, q, r, t1, t2, t3, t4)


@_kernel
def flat_contact(pc, x_prev, x):
    """Keep the vehicle on or above ``down = 0`` after a free-flight step ``x_prev -> x``.

    Contact is fully inelastic with full friction (skids on flat ground): the vehicle stops, its
    roll and pitch settle level (the landing gear rests on the plane) and its yaw is kept. It
    lifts off again as soon as thrust exceeds weight. Returns ``(x, frac)``: ``frac`` in [0, 1]
    is where in the step the vehicle came down from the air (the touchdown), -1.0 when it did not
    (in the air, or already resting).
    """
    if x[2] < 0.0:
        return x, -1.0
    d_prev, d_new = x_prev[2], x[2]
    frac = -1.0
    if d_prev < 0.0:
        frac = d_prev / (d_prev - d_new) if d_new != d_prev else 1.0
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    yaw = math.atan2(2 * qw * qz + 2 * qx * qy, 1 - 2 * (math.pow(qy, pc[22]) + qz * qz))
    rest = (
        x[0], x[1], 0.0, 0.0, 0.0, 0.0, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2),
        0.0, 0.0, 0.0, x[13], x[14], x[15], x[16],
    )  # fmt: skip
    return rest, frac


# --------------------------------------------------------------------------- rate loop


@_kernel
def _clamp_sym(v, lim):
    v = v if v < lim else lim
    return v if v > -lim else -lim


@_kernel
def _max4(a, b, c, d):  # Python's max(): the first of the largest
    m = a
    if b > m:
        m = b
    if c > m:
        m = c
    if d > m:
        m = d
    return m


@_kernel
def _min4(a, b, c, d):  # Python's min(): the first of the smallest
    m = a
    if b < m:
        m = b
    if c < m:
        m = c
    if d < m:
        m = d
    return m


@_kernel
def rate_loop(rc, rs, sp_p, sp_q, sp_r, collective, p, q, r, dt):
    """The body-rate PID and quad-X mixer of :mod:`sitl_sim.physics.rate_controller` for one
    physics step: ``(rotor thrusts (4, N), the new state rs)``. ``sp_*`` are the setpoint's rates
    (clamped here to the max rates), ``collective`` the commanded total thrust (N)."""
    e0 = _clamp_sym(sp_p, rc[12]) - p
    e1 = _clamp_sym(sp_q, rc[13]) - q
    e2 = _clamp_sym(sp_r, rc[14]) - r
    if rs[6] > 0.0:
        de0, de1, de2 = e0 - rs[3], e1 - rs[4], e2 - rs[5]
    else:
        de0, de1, de2 = e0 - e0, e1 - e1, e2 - e2
    a0 = rc[0] * e0 + rs[0] + rc[6] * de0 / dt
    a1 = rc[1] * e1 + rs[1] + rc[7] * de1 / dt
    a2 = rc[2] * e2 + rs[2] + rc[8] * de2 / dt
    # tau = J alpha + w x (J w)
    tau_x = rc[15] * a0 + rc[18] * q * r
    tau_y = rc[16] * a1 + rc[19] * r * p
    tau_z = rc[17] * a2 + rc[20] * p * q
    tmax = rc[22]
    # the mixer: roll/pitch > yaw > collective
    rp0 = rc[23] * tau_x + rc[27] * tau_y
    rp1 = rc[24] * tau_x + rc[28] * tau_y
    rp2 = rc[25] * tau_x + rc[29] * tau_y
    rp3 = rc[26] * tau_x + rc[30] * tau_y
    y0, y1, y2, y3 = rc[31] * tau_z, rc[32] * tau_z, rc[33] * tau_z, rc[34] * tau_z
    limited_rp = limited_y = False
    spread = _max4(rp0, rp1, rp2, rp3) - _min4(rp0, rp1, rp2, rp3)
    if spread > tmax:
        k = tmax / spread  # roll/pitch scaled to fit, no yaw at all
        s0, s1, s2, s3 = rp0 * k + 0.0, rp1 * k + 0.0, rp2 * k + 0.0, rp3 * k + 0.0
        limited_rp = limited_y = True
    else:
        s0, s1, s2, s3 = rp0 + y0, rp1 + y1, rp2 + y2, rp3 + y3
        if _max4(s0, s1, s2, s3) - _min4(s0, s1, s2, s3) > tmax:
            # Largest yaw fraction that still fits: spread is piecewise linear in the fraction.
            lo, hi = 0.0, 1.0
            for _ in range(20):
                mid = 0.5 * (lo + hi)
                u0, u1, u2, u3 = rp0 + mid * y0, rp1 + mid * y1, rp2 + mid * y2, rp3 + mid * y3
                if _max4(u0, u1, u2, u3) - _min4(u0, u1, u2, u3) > tmax:
                    hi = mid
                else:
                    lo = mid
            y0, y1, y2, y3 = y0 * lo, y1 * lo, y2 * lo, y3 * lo
            limited_y = True
            s0, s1, s2, s3 = rp0 + y0, rp1 + y1, rp2 + y2, rp3 + y3
    base = collective / 4.0
    lo_fit = -_min4(s0, s1, s2, s3)
    base_fit = base if not lo_fit > base else lo_fit  # max(base, -min(total))
    hi_fit = tmax - _max4(s0, s1, s2, s3)
    base_fit = base_fit if not hi_fit < base_fit else hi_fit  # min(., tmax - max(total))
    rotors = (
        _rotor(base_fit + s0, tmax),
        _rotor(base_fit + s1, tmax),
        _rotor(base_fit + s2, tmax),
        _rotor(base_fit + s3, tmax),
    )
    # A shifted collective protects the torque: thrust-limited, but the axes are not, so the
    # integrators keep running.
    saturated = limited_rp or limited_y or abs(base_fit - base) > 1e-9
    i0, i1, i2 = rs[0], rs[1], rs[2]
    if not limited_rp:
        i0 = _clamp_sym(i0 + rc[3] * e0 * dt, rc[9])
        i1 = _clamp_sym(i1 + rc[4] * e1 * dt, rc[10])
    if not limited_y:
        i2 = _clamp_sym(i2 + rc[5] * e2 * dt, rc[11])
    return rotors, (i0, i1, i2, e0, e1, e2, 1.0, 1.0 if saturated else 0.0)


@_kernel
def _rotor(d, tmax):  # min(tmax, max(0.0, d))
    d = d if d > 0.0 else 0.0
    return d if d < tmax else tmax


# --------------------------------------------------------------------------- a period


@_kernel
def period(pc, rc, x, rs, armed, sp_p, sp_q, sp_r, collective, dt, n, wn, we, wd, flat):
    """``n`` physics steps from state ``x`` holding one command and one wind.

    ``armed`` False is a disarmed autopilot: the rate loop reset and the rotors commanded to
    zero at every step. ``flat``: resolve the flat ground's contact after each step (else the
    free flight of one step is returned, ``n`` must be 1, and the caller resolves a site's).

    Returns ``(x, rotors, rs, touch)``: the state, the last rotor commands, the rate loop's
    state, and the period's first touchdown ``(j, frac, before, free)``: at step ``j`` (0-based;
    -1: none), fraction ``frac`` of it, between the states ``before`` the step and its free
    flight ``free`` (the contact point is interpolated between them; both ``x`` when none).
    """
    rotors = (0.0, 0.0, 0.0, 0.0)
    j_touch, frac_touch, before, free = -1, -1.0, x, x
    for j in range(n):
        if armed:
            rotors, rs = rate_loop(rc, rs, sp_p, sp_q, sp_r, collective, x[10], x[11], x[12], dt)
        else:
            rotors, rs = (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        x_free = integrate(pc, x, rotors[0], rotors[1], rotors[2], rotors[3], dt, wn, we, wd)
        x_new = x_free
        if flat:
            x_new, frac = flat_contact(pc, x, x_free)
            if frac >= 0.0 and j_touch < 0:
                j_touch, frac_touch, before, free = j, frac, x, x_free
        x = x_new
    return x, rotors, rs, (j_touch, frac_touch, before, free)
