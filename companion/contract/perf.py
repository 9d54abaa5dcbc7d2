"""Where a process's wall time goes while it flies: :class:`LoopPerf`, the cheap always-on
counters the SITL and the companion keep around the parts of their loops, and the report both
print at exit (:meth:`LoopPerf.report`) that ``visland bench sitl`` reads.

The window is the flight (the SITL: physics running, take-over to episode end; the companion:
a policy flight in the air, OFFBOARD confirmed to done): the handshake before it runs at
wall-clock speed on purpose and says nothing about the lockstep loop. Inside the window each
part's wall seconds are summed from :func:`time.perf_counter` stamps the loop takes anyway;
what no part claims is ``other``. The process CPU time of the window is read only where the
window opens and closes (a system call; not per pass).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

__all__ = ["CPUS_ENV", "PARTS", "PERF_LINE_PREFIX", "LoopPerf", "parse_perf_line", "pin_to_cpus"]

CPUS_ENV = {"sitl": "VISLAND_SITL_CPUS", "companion": "VISLAND_COMPANION_CPUS"}
"""The environment variables that pin a process of the pair to CPUs (:func:`pin_to_cpus`), e.g.
``VISLAND_SITL_CPUS=0 VISLAND_COMPANION_CPUS=1 visland bench sitl``: in lockstep the SITL's
datagrams wake the companion, which the kernel may then run on the SITL's CPU, beside an idle
one (each telemetry datagram's handling taken from the SITL's time); pinned apart, neither
waits for the other's CPU. Unset (the default): the kernel places both."""

PARTS = ("physics", "render", "policy", "mavlink", "camera", "log", "wait")
"""The parts of a loop pass: ``physics`` (rigid body + rate loop), ``render`` (the camera
image), ``policy`` (the network or the MPC), ``mavlink`` (messages built, sensors read for
them, packed, sent, received, decoded, dispatched), ``camera`` (frame packets encoded, sent,
received, reassembled), ``log`` (flight-log records encoded and written), ``wait`` (blocked in
``select`` for the other process or the wall clock)."""

PERF_LINE_PREFIX = "perf: "
"""How the SITL's report starts on its log (stderr) line: ``perf: {json}``."""


class LoopPerf:
    """Wall seconds per :data:`PARTS` entry inside the flight window of one process's loop.

    Use: at the top of each loop pass ``t = perf.mark(in_flight)``; after each part
    ``t = perf.add("physics", t)`` (returns the time now, for the next part). A part timed
    inside another (the flight log written from a stream's send) uses :meth:`add_inner`: its
    seconds go to it and are taken off the enclosing part's next :meth:`add`. Outside the
    window both only read the clock.

    Args:
        clock: the wall clock (seconds, monotonic).
        cpu_clock: the process CPU clock (seconds).
    """

    def __init__(
        self,
        clock: Callable[[], float] = time.perf_counter,
        cpu_clock: Callable[[], float] = time.process_time,
    ) -> None:
        self._clock = clock
        self._cpu_clock = cpu_clock
        self.parts_s: dict[str, float] = dict.fromkeys((*PARTS, "other"), 0.0)
        """Wall seconds of each part inside the window (``other``: what the owner timed as no
        part, e.g. to close a span holding inner parts; :meth:`report` gives it the rest)."""
        self.window_s = 0.0
        """Wall seconds inside the window."""
        self.cpu_s = 0.0
        """Process CPU seconds inside the window."""
        self.windows = 0
        """Times the window opened (flights)."""
        self.counts: dict[str, float] = {}
        """What the owner counts inside the window (``frames``, ``sim_s``, ``steps``)."""
        self._active = False
        self._mark = 0.0
        self._cpu_mark = 0.0
        self._inner = 0.0
        self.now = clock
        """The wall clock (a part's start stamp when no earlier :meth:`add` returned one)."""

    @property
    def active(self) -> bool:
        return self._active

    def mark(self, active: bool) -> float:
        """A loop pass starts: the pass that ended counts to the window if it was inside;
        ``active`` says whether this one is. Returns the time now."""
        now = self._clock()
        if self._active:
            self.window_s += now - self._mark
        if active != self._active:
            cpu = self._cpu_clock()
            if active:
                self._cpu_mark = cpu
                self.windows += 1
            else:
                self.cpu_s += cpu - self._cpu_mark
            self._active = active
        self._mark = now
        self._inner = 0.0
        return now

    def add(self, part: str, t0: float) -> float:
        """``part`` ran from ``t0`` until now, less the inner parts timed meanwhile (counted
        inside the window). Returns now."""
        now = self._clock()
        if self._active:
            self.parts_s[part] += now - t0 - self._inner
        self._inner = 0.0
        return now

    def add_inner(self, part: str, t0: float) -> float:
        """``part`` ran from ``t0`` until now inside a part that :meth:`add` closes later.
        Returns now."""
        now = self._clock()
        if self._active:
            self.parts_s[part] += now - t0
            self._inner += now - t0
        return now

    def count(self, name: str, amount: float = 1.0) -> None:
        """Add ``amount`` to the counter ``name`` (inside the window only)."""
        if self._active:
            self.counts[name] = self.counts.get(name, 0.0) + amount

    def close(self) -> None:
        """End the window (the loop ended): the pass in progress counts."""
        self.mark(False)

    def report(self) -> dict[str, Any]:
        """``{window_wall_s, window_cpu_s, windows, parts_s, shares, counts}``, ``parts_s``
        with ``other`` (the window's time no part claimed); ``shares`` are fractions of the
        window's wall time (summing to 1 but for rounding; all 0 for an empty window). Where
        the owner counts ``sim_s`` (the SITL: sim seconds flown), also ``realtime_factor`` =
        sim seconds per wall second of the window."""
        window, cpu = self.window_s, self.cpu_s
        if self._active:  # a report mid-window (tests): up to now
            now = self._clock()
            window += now - self._mark
            cpu += self._cpu_clock() - self._cpu_mark
        named = sum(v for k, v in self.parts_s.items() if k != "other")
        parts = {**self.parts_s, "other": max(window - named, 0.0)}
        out: dict[str, Any] = {
            "window_wall_s": window,
            "window_cpu_s": cpu,
            "windows": self.windows,
            "parts_s": parts,
            "shares": {k: (v / window if window > 0 else 0.0) for k, v in parts.items()},
            "counts": dict(self.counts),
        }
        if "sim_s" in self.counts:
            out["realtime_factor"] = self.counts["sim_s"] / window if window > 0 else 0.0
        return out


def parse_perf_line(text: str) -> dict[str, Any] | None:
    """The report in the last ``perf: {json}`` line of ``text`` (a process's log), or None."""
    import json

    for line in reversed(text.splitlines()):
        at = line.find(PERF_LINE_PREFIX + "{")
        if at >= 0:
            try:
                return json.loads(line[at + len(PERF_LINE_PREFIX) :])
            except ValueError:
                return None
    return None


def pin_to_cpus(process: str) -> tuple[int, ...] | None:
    """Pin this process to the CPUs that ``CPUS_ENV[process]`` lists (``0``, ``1,3``, ``0-2``);
    the CPUs pinned to, or None when the variable is unset or empty.

    Raises:
        ValueError: the variable is not a CPU list, or names CPUs this machine lacks.
    """
    import os

    name = CPUS_ENV[process]
    text = os.environ.get(name, "").strip()
    if not text:
        return None
    cpus: set[int] = set()
    try:
        for part in text.split(","):
            first, dash, last = part.partition("-")
            low = int(first)
            high = int(last) if dash else low
            if high < low:
                raise ValueError(f"range {part!r} runs backwards")
            cpus.update(range(low, high + 1))
        os.sched_setaffinity(0, cpus)
    except (ValueError, OSError) as exc:
        last_cpu = (os.cpu_count() or 1) - 1
        raise ValueError(
            f"{name}={text!r}: expected CPU numbers of this machine (0..{last_cpu}) such as 0, "
            f"1,3 or 0-2 ({exc})"
        ) from None
    return tuple(sorted(cpus))
