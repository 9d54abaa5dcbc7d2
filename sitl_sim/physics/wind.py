"""Wind: a mean wind, Dryden turbulence and discrete 1-cosine gusts, from a scenario's ``[wind]``.

The total wind is the sum of three NED parts, as JSBSim composes its wind
(JSBSim-Team/jsbsim ``src/models/atmosphere/FGWinds.cpp``, ``Run``):

* **mean wind**: speed and direction drawn once per episode, uniformly from the scenario's ranges.
  The direction is where the wind blows FROM (meteorological convention, 0 deg = north, 90 = east),
  so a wind from the north blows toward the south and has a negative north component.
* **Dryden turbulence** (MIL-F-8785C, low altitude): scale lengths and intensities at the
  vehicle's altitude ``h`` (in ft inside the formulas, clipped below at 10 ft as JSBSim does and
  above at 1000 ft, the top of the low-altitude model), ``sigma_w = 0.1 W20`` with W20 = 7.72 /
  15.43 / 23.15 m/s for light / moderate / severe (15 / 30 / 45 kt: MathWorks' Dryden block pages;
  the m/s values as in OpenSDSE ``Environment.hh``)::

      L_w = h,  L_u = L_v = h / (0.177 + 0.000823 h)^1.2,
      sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4

  Components along the wind axes (u along the mean wind, v to its right, w down), rotated to NED
  as JSBSim rotates them by the wind azimuth. The forming filters driven by unit white noise
  (MathWorks "Dryden Wind Turbulence Model (Continuous)", MIL-F-8785C forms, normalised so that
  their output variance is exactly sigma^2)::

      H_u(s) = sigma_u sqrt(2a_u) / (s + a_u)                      a_u = V / L_u
      H_v(s) = sigma_v sqrt(3a_v) (s + a_v/sqrt(3)) / (s + a_v)^2   a_v = V / L_v   (w likewise)

  ``V`` is the speed of the vehicle through the air mass that carries the frozen turbulence field
  (Taylor's hypothesis, the Dryden model's assumption): ``|v_ground - v_mean_wind|``, floored at
  :data:`MIN_ADVECTION_SPEED_M_S` so that a vehicle hovering in still air still sees turbulence
  evolve (with ``V -> 0`` the frozen field stops; goromal/wind-dynamics fixes V = 1 m/s).
  Each filter is discretised *exactly* for the step (the stationary Gauss-Markov step, not Euler),
  so its variance is sigma^2 at any step length; see :class:`_DrydenFilters`.
* **gusts** (optional): the 1-cosine profile of MIL-F-8785C / the MathWorks "Discrete Wind Gust
  Model", parameterised by time as JSBSim's ``CosineGustProfile`` (rise over half the gust, fall
  over the other half, no steady phase): ``g(t) = A/2 (1 - cos(2 pi (t - t0)/T))`` for
  ``t0 <= t <= t0 + T``, along the mean wind's downwind direction. Onsets are a renewal process:
  the first at ``U(0, 20)`` s, then every ``U(10, 20)`` s; durations ``U(1, 3)`` s, amplitudes
  ``U(gust_m_s)`` per gust (rates chosen, not from a standard: several gusts per landing).

Randomness: one :class:`numpy.random.Generator` per episode (:meth:`WindModel.for_episode`
derives it from ``(seed, episode index, WIND_STREAM)``, an entropy no other stream of the project
uses, so adding wind changes no other random draw). The mean wind is drawn first; turbulence noise
and the gust schedule then come from two streams spawned from it, so a change in one never shifts
the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from companion.table import Section, choice, span
from sitl_sim.errors import SimStateError

__all__ = [
    "GUST_DURATION_S",
    "GUST_FIRST_ONSET_S",
    "GUST_INTERVAL_S",
    "MIN_ADVECTION_SPEED_M_S",
    "TURBULENCE_W20_M_S",
    "WIND_STREAM",
    "DrydenParams",
    "WindConfig",
    "WindModel",
    "dryden_low_altitude",
    "wind_config_from_table",
]

TURBULENCE_W20_M_S = {"none": 0.0, "light": 7.72, "moderate": 15.43, "severe": 23.15}
"""Wind speed at 20 ft per turbulence level (15 / 30 / 45 kt); ``sigma_w = 0.1 W20``."""

MIN_ADVECTION_SPEED_M_S = 1.0
"""Floor of the frozen-field advection speed V (a hovering vehicle still sees turbulence)."""

GUST_FIRST_ONSET_S = (0.0, 20.0)
GUST_INTERVAL_S = (10.0, 20.0)
"""Time between successive gust onsets (longer than the longest gust: gusts never overlap)."""
GUST_DURATION_S = (1.0, 3.0)

WIND_STREAM = 0x57494E44
"""Third entropy word of the wind's generator (ASCII "WIND"); no other stream uses three words
with this value, so the wind's draws are independent of the sensors' and the sampler's."""


_FT = 0.3048
_H_MIN_FT = 10.0  # JSBSim FGWinds.cpp clips the altitude of the low-altitude model at 10 ft
_H_MAX_FT = 1000.0  # MIL-F-8785C low-altitude model: h < 1000 ft


@dataclass(frozen=True)
class WindConfig(Section):
    """The ``[wind]`` section: ranges ``(lo, hi)`` sampled per episode, turbulence and gusts
    (each key's unit, default and range: its declaration, :mod:`companion.table`).

    Attributes:
        speed_m_s: mean horizontal wind speed range, m/s (``0 <= lo <= hi <= 50``).
        direction_deg: range of the direction the wind blows FROM, deg (0 = north, 90 = east).
        turbulence: ``"none"``, ``"light"``, ``"moderate"`` or ``"severe"`` (Dryden).
        gust_m_s: 1-cosine gust amplitude range, m/s, or None for no gusts.
        source: the file it came from (for error messages).
    """

    SECTION: ClassVar[str] = "wind"

    speed_m_s: tuple[float, float] = span(
        unit="m/s",
        lo=0.0,
        hi=50.0,
        doc="mean horizontal wind speed, drawn per episode (50 m/s: a category-3 hurricane)",
    )
    direction_deg: tuple[float, float] = span(
        unit="deg",
        lo=-360.0,
        hi=360.0,
        doc="where the mean wind blows FROM (0 = north, 90 = east), drawn per episode",
    )
    turbulence: str = choice(
        "none", TURBULENCE_W20_M_S, doc="Dryden turbulence level (MIL-F-8785C, low altitude)"
    )
    gust_m_s: tuple[float, float] | None = span(
        None,
        unit="m/s",
        lo=0.0,
        hi=30.0,
        doc="1-cosine gust amplitude, drawn per gust (absent: no gusts)",
    )


def wind_config_from_table(table: Any, where: str) -> WindConfig:
    """Check and type a scenario file's ``[wind]`` table (``where`` names the file)."""
    return WindConfig.from_table(table, where)


# --------------------------------------------------------------------------- Dryden parameters


@dataclass(frozen=True)
class DrydenParams:
    """MIL-F-8785C low-altitude scale lengths (m) and intensities (m/s) at one altitude."""

    length_u_m: float
    length_v_m: float
    length_w_m: float
    sigma_u_m_s: float
    sigma_v_m_s: float
    sigma_w_m_s: float


def dryden_low_altitude(altitude_m: float, w20_m_s: float) -> DrydenParams:
    """MIL-F-8785C low-altitude Dryden lengths and intensities (JSBSim ``FGWinds.cpp``, which
    cites MIL-F-8785C Figs. 10-11), with ``h`` clipped to [10, 1000] ft."""
    h_ft = min(max(altitude_m / _FT, _H_MIN_FT), _H_MAX_FT)
    k = 0.177 + 0.000823 * h_ft
    length_w_ft = h_ft
    length_u_ft = h_ft / k**1.2
    sigma_w = 0.1 * w20_m_s
    sigma_u = sigma_w / k**0.4
    return DrydenParams(
        length_u_m=length_u_ft * _FT,
        length_v_m=length_u_ft * _FT,
        length_w_m=length_w_ft * _FT,
        sigma_u_m_s=sigma_u,
        sigma_v_m_s=sigma_u,
        sigma_w_m_s=sigma_w,
    )


# --------------------------------------------------------------------------- forming filters

# Series of f1(y) = 1 - e^-y (1 + y) and f2(y) = 2 - e^-y (2 + 2y + y^2) about y = 0 (their closed
# forms cancel catastrophically for the small y = 2 a dt of a long scale length):
# f1 = sum_{n>=2} (-1)^n (n-1) y^n / n!,  f2 = sum_{n>=3} (-1)^(n+1) (n-1)(n-2) y^n / n!.
_SERIES_BELOW = 0.5  # below: the series (18 terms, last ~1e-22 relative); above: closed forms
_SHORT_BELOW = 0.05  # below: 8 terms already reach ~2e-16 relative (the usual case: L >> V dt)
_F1_COEF = tuple((-1) ** n * (n - 1) / math.factorial(n) for n in range(2, 20))
_F2_COEF = tuple((-1) ** (n + 1) * (n - 1) * (n - 2) / math.factorial(n) for n in range(3, 21))
_F1_SHORT, _F2_SHORT = _F1_COEF[:8], _F2_COEF[:8]


def _horner(coef: tuple[float, ...], y: float) -> float:
    acc = 0.0
    for c in reversed(coef):
        acc = acc * y + c
    return acc


def _f1(y: float) -> float:
    if y < _SHORT_BELOW:
        return y * y * _horner(_F1_SHORT, y)
    if y < _SERIES_BELOW:
        return y * y * _horner(_F1_COEF, y)
    return -math.expm1(-y) - y * math.exp(-y)


def _f2(y: float) -> float:
    if y < _SHORT_BELOW:
        return y * y * y * _horner(_F2_SHORT, y)
    if y < _SERIES_BELOW:
        return y * y * y * _horner(_F2_COEF, y)
    return 2.0 - math.exp(-y) * (2.0 + 2.0 * y + y * y)


_LEAD = 1.0 - 1.0 / math.sqrt(3.0)
_GAIN_VW = math.sqrt(1.5)


class _DrydenFilters:
    """The three forming filters on unit-variance states (output = sigma x state).

    * u: Ornstein-Uhlenbeck ``x' = -a x + sqrt(2a) xi``; exact step
      ``x <- e^{-a dt} x + sqrt(1 - e^{-2 a dt}) eta``.
    * v, w: ``H(s) = sqrt(3a) (s + a/sqrt3)/(s + a)^2`` split as ``sqrt(2a)/(s + a)`` (the same OU
      state x1) followed by ``sqrt(3/2) (s + a/sqrt3)/(s + a)``, i.e. a low-pass
      ``z' = a (x1 - z)`` and output ``y = sqrt(3/2) (x1 - (1 - 1/sqrt3) z)``. The pair (x1, z) has
      ``Phi = e^{-a dt} [[1, 0], [a dt, 1]]`` and, in units of 1/a, a stationary covariance
      independent of a: ``P = [[1, 1/2], [1/2, 1/2]]`` (so var y = 1). The exact discrete noise
      is ``Q = P - Phi P Phi^T``: ``q11 = 1 - e^{-2x}``, ``q12 = f1(2x)/2``, ``q22 = f2(2x)/4``
      with ``x = a dt``. Because P does not depend on a, V and L may change from step to step (a
      descending vehicle) and the states stay unit-variance: only sigma(h) scales the output.
    """

    _BLOCK = 4096  # normal draws are taken in blocks: per-scalar calls dominate otherwise

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._noise: list[float] = []
        self._next = 0
        # Start in the stationary distribution: turbulence is already developed at t = 0.
        e = self._normals(5)
        self.xu = e[0]
        self.xv, self.zv = e[1], 0.5 * e[1] + 0.5 * e[2]  # Cholesky of P: [[1, 0], [1/2, 1/2]]
        self.xw, self.zw = e[3], 0.5 * e[3] + 0.5 * e[4]

    def _normals(self, n: int) -> list[float]:
        if self._next + n > len(self._noise):
            self._noise = self._rng.standard_normal(self._BLOCK).tolist()
            self._next = 0
        out = self._noise[self._next : self._next + n]
        self._next += n
        return out

    @staticmethod
    def _second_order(x1: float, z: float, x: float, e1: float, e2: float) -> tuple[float, float]:
        decay = math.exp(-x)
        q11 = -math.expm1(-2.0 * x)
        q12 = 0.5 * _f1(2.0 * x)
        q22 = 0.25 * _f2(2.0 * x)
        l11 = math.sqrt(q11)
        l21 = q12 / l11
        l22 = math.sqrt(max(q22 - l21 * l21, 0.0))
        return decay * x1 + l11 * e1, decay * (x * x1 + z) + l21 * e1 + l22 * e2

    def advance(self, dt: float, speed: float, p: DrydenParams) -> None:
        e = self._normals(5)
        xu = speed * dt / p.length_u_m
        self.xu = math.exp(-xu) * self.xu + math.sqrt(-math.expm1(-2.0 * xu)) * e[0]
        self.xv, self.zv = self._second_order(
            self.xv, self.zv, speed * dt / p.length_v_m, e[1], e[2]
        )
        self.xw, self.zw = self._second_order(
            self.xw, self.zw, speed * dt / p.length_w_m, e[3], e[4]
        )

    def output(self, p: DrydenParams) -> tuple[float, float, float]:
        """(u, v, w) in m/s, wind axes."""
        return (
            p.sigma_u_m_s * self.xu,
            p.sigma_v_m_s * _GAIN_VW * (self.xv - _LEAD * self.zv),
            p.sigma_w_m_s * _GAIN_VW * (self.xw - _LEAD * self.zw),
        )


# --------------------------------------------------------------------------- the model


class WindModel:
    """The wind of one episode, advanced once per physics step.

    Args:
        config: the scenario's ``[wind]``.
        rng: this episode's wind generator (see :meth:`for_episode`); the model owns it.

    Use: :meth:`start` at the initial state (the simulator's ``reset`` does it), then
    :meth:`step` once per physics step. ``step`` returns the wind to hold over that step (zero-order
    hold: the integrator sees one constant wind for the whole RK4 step) and moves the model to
    the end of the step; :attr:`wind_ned_m_s` is the wind at the model's current time, i.e. what
    the next step will hold.
    """

    def __init__(self, config: WindConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.speed_m_s = float(rng.uniform(*config.speed_m_s))
        self.direction_deg = float(rng.uniform(*config.direction_deg))
        psi = math.radians(self.direction_deg)
        # FROM convention: the wind blows toward psi + 180 deg.
        self._along = (-math.cos(psi), -math.sin(psi))  # downwind unit vector (N, E)
        self._right = (-self._along[1], self._along[0])  # +90 deg about down: right of downwind
        self._mean = (self.speed_m_s * self._along[0], self.speed_m_s * self._along[1], 0.0)
        turb_rng, gust_rng = rng.spawn(2)
        self._w20 = TURBULENCE_W20_M_S[config.turbulence]
        self._filters = _DrydenFilters(turb_rng) if self._w20 > 0.0 else None
        self._gust_rng = gust_rng
        self._gust: tuple[float, float, float] | None = None  # (onset, duration, amplitude)
        if config.gust_m_s is not None:
            self._gust = self._draw_gust(float(gust_rng.uniform(*GUST_FIRST_ONSET_S)))
        self._params: DrydenParams | None = None
        self._turb = (0.0, 0.0, 0.0)
        self._gust_m_s = 0.0
        self._wind: tuple[float, float, float] | None = None
        self.time_s = 0.0

    @classmethod
    def for_episode(cls, config: WindConfig, seed: int, episode_index: int) -> WindModel:
        """The wind of episode ``episode_index`` of ``seed``: a pure function of the three."""
        return cls(config, np.random.default_rng([int(seed), int(episode_index), WIND_STREAM]))

    # ------------------------------------------------------------------ state

    @property
    def started(self) -> bool:
        return self._wind is not None

    @property
    def mean_wind_ned_m_s(self) -> np.ndarray:
        return np.array(self._mean)

    @property
    def wind_ned_m_s(self) -> np.ndarray:
        """(3,) total wind (NED, m/s) at :attr:`time_s`."""
        return np.array(self._current())

    @property
    def wind_tuple(self) -> tuple[float, float, float]:
        """:attr:`wind_ned_m_s` as Python floats (for the integrator)."""
        return self._current()

    @property
    def turbulence_wind_axes_m_s(self) -> tuple[float, float, float]:
        """(u, v, w) turbulence at :attr:`time_s`: along the mean wind, to its right, down."""
        return self._turb

    @property
    def gust_m_s(self) -> float:
        """The gust's speed along the downwind direction at :attr:`time_s`."""
        return self._gust_m_s

    @property
    def dryden(self) -> DrydenParams | None:
        """The Dryden lengths and intensities last used (None before :meth:`start`)."""
        return self._params

    def _current(self) -> tuple[float, float, float]:
        if self._wind is None:
            raise SimStateError("WindModel.start() must be called before reading the wind")
        return self._wind

    # ------------------------------------------------------------------ advancing

    def start(self, pos_ned_m, t_s: float = 0.0) -> None:
        """Set the wind at ``t_s`` for a vehicle at ``pos_ned_m`` (once per model: a model
        serves one episode; build a fresh one for a replay)."""
        if self._wind is not None:
            raise SimStateError("WindModel already started: build a fresh one per episode")
        self._params = dryden_low_altitude(-float(pos_ned_m[2]), self._w20)
        self._compose(t_s)

    def step(self, dt: float, t_s: float, pos_ned_m, vel_ned_m_s) -> tuple[float, float, float]:
        """The wind (NED, m/s, Python floats) to hold over the physics step ``[t_s, t_s + dt)``;
        advances the turbulence filters to ``t_s + dt`` with the vehicle's state at ``t_s``."""
        if self._wind is None:
            self.start(pos_ned_m, t_s)
        held = self._wind
        assert held is not None
        if self._filters is not None:
            # Taylor's frozen field rides on the mean wind: V is the speed through that air mass.
            rel_n = float(vel_ned_m_s[0]) - self._mean[0]
            rel_e = float(vel_ned_m_s[1]) - self._mean[1]
            rel_d = float(vel_ned_m_s[2])
            speed = max(
                math.sqrt(rel_n * rel_n + rel_e * rel_e + rel_d * rel_d), MIN_ADVECTION_SPEED_M_S
            )
            self._params = dryden_low_altitude(-float(pos_ned_m[2]), self._w20)
            self._filters.advance(dt, speed, self._params)
        self._compose(t_s + dt)
        return held

    def _compose(self, t_s: float) -> None:
        self.time_s = t_s
        if self._filters is not None and self._params is not None:
            self._turb = self._filters.output(self._params)
        self._gust_m_s = self._gust_at(t_s)
        u, v, w = self._turb
        along = u + self._gust_m_s
        an, ae = self._along
        rn, re = self._right
        if self._filters is None and self._gust is None:
            self._wind = self._mean  # "none" and no gusts: exactly the mean wind
        else:
            self._wind = (
                self._mean[0] + along * an + v * rn,
                self._mean[1] + along * ae + v * re,
                w,
            )

    def _draw_gust(self, onset_s: float) -> tuple[float, float, float]:
        assert self.config.gust_m_s is not None
        duration = float(self._gust_rng.uniform(*GUST_DURATION_S))
        amplitude = float(self._gust_rng.uniform(*self.config.gust_m_s))
        return onset_s, duration, amplitude

    def _gust_at(self, t_s: float) -> float:
        if self._gust is None:
            return 0.0
        onset, duration, amplitude = self._gust
        while t_s > onset + duration:  # past this gust: schedule the next (time only advances)
            onset += float(self._gust_rng.uniform(*GUST_INTERVAL_S))
            self._gust = self._draw_gust(onset)
            onset, duration, amplitude = self._gust
        if t_s < onset:
            return 0.0
        return 0.5 * amplitude * (1.0 - math.cos(2.0 * math.pi * (t_s - onset) / duration))
