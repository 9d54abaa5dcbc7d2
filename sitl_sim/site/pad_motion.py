"""How the pad moves: static, on a rover's roof, on a ship's deck — kinematic paths of sim time.

Each model gives the pose of the pad's surface centre (the roof or deck it lies on: the pad's own
layers are drawn a few centimetres above it) as ``(position_ned, R_pad_to_ned)`` at any sim time
``t``; :class:`PadPose` adds the velocity and angular velocity (central differences of the path,
1 ms apart: exact to ~1e-6 for these smooth paths). The pad frame is x forward (the vehicle's
heading), y right, z down, as a vehicle's FRD; at ``t = 0`` the pad's centre is above the world
origin (the pad the scenario's initial states are drawn around), ``height_m`` above the ground.

- :class:`StaticPad` — still; tilted with the ground under it (a slope).
- :class:`RoverPad` — drives at a constant speed from heading ``heading``; the heading integrates
  a turn rate that wanders within ``[turn_lo, turn_hi]`` (two slow sinusoids with random phases:
  it drives curves and S-bends; ``[r, r]`` is a circle, ``[0, 0]`` a straight line). It follows
  the ground: its height and tilt are the terrain's (rocks aside) under its centre.
- :class:`DeckPad` — a ship's deck at sea: heave, roll and pitch each a sum of three sinusoids
  with random phases (a sea state's spectrum, cut to three lines) whose peak never exceeds the
  drawn amplitude, and a slow straight drift at ``speed`` along ``heading``.

``ground(n, e) -> (height_up_m, (dh_dn, dh_de))`` is the terrain under a rover (None: flat at 0).
Pure numpy and math; no rendering.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from companion.contract import rotation_zyx

__all__ = [
    "DeckPad",
    "MotionSpans",
    "PadMotion",
    "PadPose",
    "RoverPad",
    "StaticPad",
    "draw_pad_motion",
    "frame_from_down",
]

Ground = Callable[[float, float], tuple[float, tuple[float, float]]]
_DIFF_S = 1e-3  # central-difference step for velocities (s)
_TABLE_DT = 0.1  # the rover's integrated path is tabulated every 0.1 s


@dataclass(frozen=True)
class PadPose:
    """The pad's surface centre at one time: position (NED, m), rotation pad->NED (columns: the
    pad's forward, right and down axes in NED), velocity (NED, m/s) and angular velocity (NED,
    rad/s)."""

    position_ned: np.ndarray
    R_pad_to_ned: np.ndarray
    velocity_ned: np.ndarray
    omega_ned: np.ndarray


def frame_from_down(down: np.ndarray, heading: float) -> np.ndarray:
    """The frame whose z axis is ``down`` (unit, NED) and whose x axis points along ``heading``
    (from north, clockwise) as nearly as a frame square to ``down`` can."""
    k0, k1, k2 = (float(v) for v in down)
    f0, f1 = math.cos(heading), math.sin(heading)
    dot = f0 * k0 + f1 * k1
    x0, x1, x2 = f0 - dot * k0, f1 - dot * k1, -dot * k2
    norm = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    x0, x1, x2 = x0 / norm, x1 / norm, x2 / norm
    y0, y1, y2 = k1 * x2 - k2 * x1, k2 * x0 - k0 * x2, k0 * x1 - k1 * x0  # y = k x x
    return np.array([[x0, y0, k0], [x1, y1, k1], [x2, y2, k2]])


def _down_of(gradient: tuple[float, float]) -> tuple[float, float, float]:
    """The ground's downward unit normal (NED) for a height gradient (dh/dn, dh/de)."""
    gn, ge = gradient
    norm = math.sqrt(gn * gn + ge * ge + 1.0)
    return (gn / norm, ge / norm, 1.0 / norm)


class PadMotion(ABC):
    """Base of the motion models: :meth:`frame` is the pose at ``t``; :meth:`pose` adds rates."""

    kind = "static"
    height_m: float  # the surface the pad lies on above the ground (a dataclass field below)

    @abstractmethod
    def frame(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``(position_ned (3,), R_pad_to_ned (3, 3))`` at sim time ``t``."""

    @property
    def moves(self) -> bool:
        return True

    def pose(self, t: float) -> PadPose:
        p, r = self.frame(t)
        if not self.moves:
            return PadPose(p, r, np.zeros(3), np.zeros(3))
        p1, r1 = self.frame(t + _DIFF_S)
        p0, r0 = self.frame(t - _DIFF_S)
        v = (p1 - p0) / (2 * _DIFF_S)
        w = (r1 - r0) / (2 * _DIFF_S) @ r.T  # skew(omega) = R' R^T
        omega = np.array([w[2, 1] - w[1, 2], w[0, 2] - w[2, 0], w[1, 0] - w[0, 1]]) / 2
        return PadPose(p, r, v, omega)

    @abstractmethod
    def record(self) -> dict[str, Any]:
        """What was drawn (for the episode's log)."""


def _travel_record(pad: RoverPad | DeckPad) -> dict[str, Any]:
    """The keys a travelling pad's record starts with: its motion, height, speed and start
    heading."""
    return {
        "motion": pad.kind,
        "height_m": pad.height_m,
        "speed_m_s": pad.speed_m_s,
        "heading_deg": math.degrees(pad.heading_rad),
    }


@dataclass(frozen=True)
class StaticPad(PadMotion):
    """A still pad ``height_m`` above the ground at the origin, square to the ground there
    (``ground_gradient``: the slope under it)."""

    height_m: float = 0.0
    ground_gradient: tuple[float, float] = (0.0, 0.0)
    kind = "static"

    @property
    def moves(self) -> bool:
        return False

    def frame(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        return np.array([0.0, 0.0, -self.height_m]), frame_from_down(
            _down_of(self.ground_gradient), 0.0
        )

    def record(self) -> dict[str, Any]:
        return {"motion": "static", "height_m": self.height_m}


@dataclass(frozen=True, eq=False)
class RoverPad(PadMotion):
    """A pad on a rover's roof ``height_m`` above the ground (see the module docstring)."""

    height_m: float
    speed_m_s: float
    heading_rad: float
    turn_lo_rad_s: float
    turn_hi_rad_s: float
    turn_omega_rad_s: tuple[float, float]
    turn_phase_rad: tuple[float, float]
    ground: Ground | None = field(default=None, repr=False)
    _table: list[tuple[float, float]] = field(default_factory=lambda: [(0.0, 0.0)], repr=False)
    kind = "rover"

    _WEIGHTS = (0.6, 0.4)

    def heading(self, t: float) -> float:
        """Heading (rad from north) at ``t``: the integral of the turn rate."""
        mid = 0.5 * (self.turn_lo_rad_s + self.turn_hi_rad_s)
        half = 0.5 * (self.turn_hi_rad_s - self.turn_lo_rad_s)
        psi = self.heading_rad + mid * t
        for w, om, ph in zip(
            self._WEIGHTS, self.turn_omega_rad_s, self.turn_phase_rad, strict=True
        ):
            psi += half * w * (math.cos(ph) - math.cos(om * t + ph)) / om
        return psi

    def turn_rate(self, t: float) -> float:
        """Turn rate (rad/s) at ``t``: within ``[turn_lo, turn_hi]`` at all times."""
        mid = 0.5 * (self.turn_lo_rad_s + self.turn_hi_rad_s)
        half = 0.5 * (self.turn_hi_rad_s - self.turn_lo_rad_s)
        return mid + half * sum(
            w * math.sin(om * t + ph)
            for w, om, ph in zip(
                self._WEIGHTS, self.turn_omega_rad_s, self.turn_phase_rad, strict=True
            )
        )

    def _simpson(self, t0: float, t1: float) -> tuple[float, float]:
        """``integral of speed (cos, sin)(heading)`` over [t0, t1] (Simpson, 3 points)."""
        h = t1 - t0
        s0, sm, s1 = self.heading(t0), self.heading(0.5 * (t0 + t1)), self.heading(t1)
        k = self.speed_m_s * h / 6.0
        return (
            k * (math.cos(s0) + 4 * math.cos(sm) + math.cos(s1)),
            k * (math.sin(s0) + 4 * math.sin(sm) + math.sin(s1)),
        )

    def plan_position(self, t: float) -> tuple[float, float]:
        """North and east of the rover's centre at ``t`` (the path on the map)."""
        if t < 0.0:  # before the flight (a delayed camera's first frames): the path backwards
            n = max(1, math.ceil(-t / _TABLE_DT))
            acc_n = acc_e = 0.0
            for i in range(n):
                dn, de = self._simpson(t * i / n, t * (i + 1) / n)
                acc_n, acc_e = acc_n + dn, acc_e + de
            return acc_n, acc_e
        k = int(t / _TABLE_DT)
        table = self._table
        while len(table) <= k:
            j = len(table) - 1
            dn, de = self._simpson(j * _TABLE_DT, (j + 1) * _TABLE_DT)
            table.append((table[j][0] + dn, table[j][1] + de))
        dn, de = self._simpson(k * _TABLE_DT, t)
        return table[k][0] + dn, table[k][1] + de

    def frame(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        n, e = self.plan_position(t)
        h, grad = self.ground(n, e) if self.ground is not None else (0.0, (0.0, 0.0))
        r = frame_from_down(_down_of(grad), self.heading(t))
        # the roof's centre: height_m above the ground along the rover's up axis
        return np.array([n, e, -h]) - self.height_m * r[:, 2], r

    def record(self) -> dict[str, Any]:
        return {
            **_travel_record(self),
            "turn_rate_deg_s": [math.degrees(self.turn_lo_rad_s), math.degrees(self.turn_hi_rad_s)],
            "turn_period_s": [2 * math.pi / om for om in self.turn_omega_rad_s],
            "turn_phase_rad": list(self.turn_phase_rad),
        }


@dataclass(frozen=True)
class DeckPad(PadMotion):
    """A pad on a ship's deck, ``height_m`` (freeboard) above the mean water level."""

    height_m: float
    speed_m_s: float
    heading_rad: float
    heave_m: float
    roll_rad: float
    pitch_rad: float
    periods_s: tuple[tuple[float, float, float], ...]  # heave, roll, pitch: three lines each
    phases_rad: tuple[tuple[float, float, float], ...]
    kind = "deck"

    WEIGHTS = (0.6, 0.25, 0.15)
    """Shares of the three lines: they sum to 1, so a motion never exceeds its amplitude."""

    def _wave(self, which: int, t: float) -> float:
        return sum(
            w * math.sin(2 * math.pi * t / p + ph)
            for w, p, ph in zip(
                self.WEIGHTS, self.periods_s[which], self.phases_rad[which], strict=True
            )
        )

    def motion(self, t: float) -> tuple[float, float, float]:
        """(heave up (m), roll (rad), pitch (rad)) at ``t``."""
        return (
            self.heave_m * self._wave(0, t),
            self.roll_rad * self._wave(1, t),
            self.pitch_rad * self._wave(2, t),
        )

    def frame(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        heave, roll, pitch = self.motion(t)
        c, s = math.cos(self.heading_rad), math.sin(self.heading_rad)
        d = self.speed_m_s * t
        return (
            np.array([c * d, s * d, -(self.height_m + heave)]),
            rotation_zyx(roll, pitch, self.heading_rad),
        )

    def record(self) -> dict[str, Any]:
        return {
            **_travel_record(self),
            "heave_m": self.heave_m,
            "roll_deg": math.degrees(self.roll_rad),
            "pitch_deg": math.degrees(self.pitch_rad),
            "periods_s": [list(p) for p in self.periods_s],
            "phases_rad": [list(p) for p in self.phases_rad],
        }


class MotionSpans(Protocol):
    """The ``[pad]`` section's motion keys (:class:`sitl_sim.render.pad_section.PadConfig`):
    the motion's name and the ``[lo, hi]`` span of each of its numbers."""

    motion: str
    height_m: tuple[float, float]
    speed_m_s: tuple[float, float]
    heading_deg: tuple[float, float]
    turn_rate_deg_s: tuple[float, float]
    heave_m: tuple[float, float]
    heave_period_s: tuple[float, float]
    roll_deg: tuple[float, float]
    pitch_deg: tuple[float, float]


def draw_pad_motion(
    rng: np.random.Generator,
    spans: MotionSpans,
    ground: Ground | None = None,
    ground_gradient: tuple[float, float] = (0.0, 0.0),
) -> PadMotion:
    """One episode's motion from the ``[pad]`` section's ``spans`` (each drawn uniformly, in
    this order: height, speed, heading, then the model's own draws)."""

    def u(rg: tuple[float, float]) -> float:
        return float(rg[0] + (rg[1] - rg[0]) * rng.random())

    height = u(spans.height_m)
    speed = u(spans.speed_m_s)
    heading = math.radians(u(spans.heading_deg))
    motion = spans.motion
    if motion == "static":
        return StaticPad(height_m=height, ground_gradient=ground_gradient)
    if motion == "rover":
        periods = (rng.uniform(20.0, 40.0), rng.uniform(8.0, 16.0))
        return RoverPad(
            height_m=height,
            speed_m_s=speed,
            heading_rad=heading,
            turn_lo_rad_s=math.radians(spans.turn_rate_deg_s[0]),
            turn_hi_rad_s=math.radians(spans.turn_rate_deg_s[1]),
            turn_omega_rad_s=tuple(2 * math.pi / p for p in periods),  # type: ignore[arg-type]
            turn_phase_rad=tuple(float(v) for v in rng.uniform(0.0, 2 * math.pi, 2)),  # type: ignore[arg-type]
            ground=ground,
        )
    if motion != "deck":
        raise ValueError(f"pad motion {motion!r}; expected static, rover or deck")
    amplitudes = (
        u(spans.heave_m),
        math.radians(u(spans.roll_deg)),
        math.radians(u(spans.pitch_deg)),
    )
    base = u(spans.heave_period_s)
    periods, phases = [], []
    for scale in (1.0, 1.15, 0.9):  # roll and pitch a little slower/faster than heave
        t0 = base * scale
        periods.append((t0, t0 * float(rng.uniform(0.55, 0.8)), t0 * float(rng.uniform(1.2, 1.6))))
        phases.append(tuple(float(v) for v in rng.uniform(0.0, 2 * math.pi, 3)))
    return DeckPad(
        height_m=height,
        speed_m_s=speed,
        heading_rad=heading,
        heave_m=amplitudes[0],
        roll_rad=amplitudes[1],
        pitch_rad=amplitudes[2],
        periods_s=tuple(periods),  # type: ignore[arg-type]
        phases_rad=tuple(phases),  # type: ignore[arg-type]
    )
