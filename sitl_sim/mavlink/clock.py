"""The SITL's time: the sim clock in whole physics steps, the lockstep wait for the companion's
answer to a camera frame, and the wall-clock pacing of the phases nobody paces.

The clock is the only time the outside world sees (``time_boot_ms``/``time_usec`` = time since
SITL start, monotonic across episodes). Lockstep stops it after each camera frame in OFFBOARD
until the frame is answered or ``lockstep_timeout_s`` of wall time passes; :class:`Pacer` keeps
it at ``speed`` × wall time where it runs paced (real time throughout, HOLD always).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FrameWait", "Pacer", "SimClock"]

_MAX_LAG_S = 0.5
"""A paced clock further behind the wall than this (machine busy) re-anchors instead of
bursting to catch up."""


@dataclass
class SimClock:
    """Sim time in physics steps (4 ms at 250 Hz) since SITL start.

    ``phase_tick`` is the tick streams and control periods count from: an episode's start, then
    its flight's start (a stream or control period is due when ``phase % period == 0``).
    """

    rate_hz: int
    dt_s: float
    tick: int = 0
    phase_tick: int = 0

    @property
    def time_s(self) -> float:
        """Sim seconds since start (MAVLink time_boot_ms / 1000)."""
        return self.tick * self.dt_s

    @property
    def time_us(self) -> int:
        return self.tick * 1_000_000 // self.rate_hz

    @property
    def time_boot_ms(self) -> int:
        """``time_boot_ms`` as MAVLink sends it (uint32, wraps)."""
        return (self.time_us // 1000) & 0xFFFFFFFF

    @property
    def phase(self) -> int:
        """Ticks since ``phase_tick``."""
        return self.tick - self.phase_tick

    def restart_phase(self) -> None:
        self.phase_tick = self.tick


@dataclass
class FrameWait:
    """Lockstep: the frame the companion must answer before the clock moves on."""

    frame_id: int
    frame_time_ms: int
    deadline_wall_s: float
    answered: bool = False

    def answers(self, time_boot_ms: int, require_stamp: bool) -> bool:
        """Whether a setpoint stamped ``time_boot_ms`` answers this frame: any setpoint does
        unless ``require_stamp`` (then it must be stamped at or after the frame's time)."""
        return not require_stamp or time_boot_ms >= self.frame_time_ms

    def pending(self, now_wall_s: float) -> bool:
        """Still unanswered and within its deadline (the clock stays stopped)."""
        return not self.answered and now_wall_s < self.deadline_wall_s


class Pacer:
    """Real-time pacing: while paced, tick ``n`` is due at ``origin + n·dt / speed`` of wall
    time, counted from where pacing (re)started; unpaced, every tick is due at once.

    Args:
        dt_s: sim seconds per tick.
        speed: sim seconds per wall second.
    """

    def __init__(self, dt_s: float, speed: float) -> None:
        self._dt = dt_s
        self._speed = speed
        self._origin: tuple[float, int] = (0.0, 0)
        self._paced: bool | None = None
        self.overruns = 0
        """Times the paced clock fell more than 0.5 s behind the wall and re-anchored."""

    def delay_s(self, now_wall_s: float, tick: int, paced: bool) -> float:
        """Wall seconds until tick ``tick + 1`` is due; 0 when it is due now."""
        if paced != self._paced:
            self._origin, self._paced = (now_wall_s, tick), paced
        if not paced:
            return 0.0
        target = self._origin[0] + (tick + 1 - self._origin[1]) * self._dt / self._speed
        if target > now_wall_s:
            return target - now_wall_s
        if now_wall_s - target > _MAX_LAG_S:  # fell behind (machine busy): re-anchor, no burst
            self.overruns += 1
            self._origin = (now_wall_s, tick)
        return 0.0
