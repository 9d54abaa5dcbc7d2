"""Link impairment from a scenario's ``[link]``: a lossy, late, duplicating, reordering telemetry
link between the SITL and the companion, applied to the datagrams the SITL sends and receives.

A real telemetry link (a radio, Wi-Fi, a cellular modem) drops and delays packets; the companion
under test must fly through that, and the autopilot's failsafes must still fire when the link is
really gone. The impairment lives in the SITL's UDP layer, so the companion is the real,
unmodified process: every datagram the SITL would send (MAVLink to the companion, camera
frames) and every datagram it receives (MAVLink from the companion) passes through one
:class:`ImpairedStream` per direction and kind, which decides its fate when it is offered and
holds it in a queue until its release time.

Keys (all optional; absent = that impairment is off, so an empty ``[link]`` is a perfect link):

* ``loss_prob``: each datagram is lost with this probability (independently).
* ``delay_ms``: fixed one-way delay, ms.
* ``jitter_ms``: extra delay drawn uniformly from ``[0, jitter_ms]`` per datagram. A stream stays
  in order (its datagrams leave a queue, as on a radio or serial link: a datagram is never
  released before one offered earlier), so jitter alone never reorders.
* ``duplicate_prob``: a delivered datagram is also delivered a second time, with its own delay
  draw (after the original, in order).
* ``reorder_prob``: the datagram jumps the queue, as ``tc-netem``'s ``reorder``: it is released
  at once, ahead of every earlier datagram still held. It needs a delay to overtake
  (``delay_ms + jitter_ms > 0``).
* ``outage_s = [start, end]``: flight seconds (time since the episode's flight started) during
  which the link is dead, both directions and the camera: every datagram is dropped (counted as
  ``outage``, not ``lost``). ``end`` may be far beyond the flight: the link is cut for good.

**Real time only.** Delays are wall-clock time: they mean something only where the SITL follows
the wall clock. In lockstep the SITL's clock stops until the companion answers each frame, so a
held answer would stop the world instead of arriving late; a SITL in lockstep with an active
``[link]`` refuses to start (:class:`~sitl_sim.errors.ConfigError`). In process (``visland
eval``, ``collect``) there is no link: the section is ignored there.

Randomness, as :mod:`sitl_sim.physics.sensor_faults`: one generator per episode keyed by ``(seed,
episode index, LINK_STREAM)``, spawned into one per stream, so the camera's datagrams never
shift the MAVLink streams' fates. Each datagram takes exactly five uniforms (loss, duplicate,
reorder, its jitter, the duplicate's jitter) whatever the settings, so the ``k``-th datagram of
a stream has the same fate for the same seed and episode, and turning one impairment on never
changes another's draws. In real time *which* datagram is the ``k``-th depends on timing; the
fates do not.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np

from companion.table import Section, number, probability, section_keys, span
from sitl_sim.errors import ConfigError

__all__ = [
    "LINK_KEYS",
    "LINK_STREAM",
    "STREAMS",
    "ImpairedStream",
    "LinkConfig",
    "LinkImpairment",
    "StreamStats",
    "link_config_from_table",
]

LINK_STREAM = 0x4C494E4B
"""Third entropy word of the link impairment's generator (ASCII "LINK"); distinct from every
other section's stream (:mod:`sitl_sim.world`)."""

STREAMS = ("mavlink_tx", "mavlink_rx", "camera_tx")
"""The impaired streams, as the SITL sees them: MAVLink it sends (to the companion), MAVLink it
receives (from the companion), camera frames it sends."""

MAX_DELAY_MS = 10_000.0
"""Upper bound of ``delay_ms + jitter_ms``: beyond COM_OF_LOSS_T (1 s) many times over, a
delayed link is a dead one; ten seconds is far past anything worth simulating."""

_DRAWS_PER_DATAGRAM = 5


def _delay(doc: str) -> Any:
    return number(0.0, unit="ms", lo=0.0, noun="a finite delay", doc=doc)


@dataclass(frozen=True)
class LinkConfig(Section):
    """The ``[link]`` section (0 / None: that impairment is off).

    Attributes:
        loss_prob: probability that a datagram is lost, in [0, 1].
        delay_ms: fixed one-way delay, ms (>= 0).
        jitter_ms: uniform extra delay ``[0, jitter_ms]`` per datagram, ms (>= 0).
        duplicate_prob: probability that a delivered datagram arrives twice, in [0, 1].
        reorder_prob: probability that a datagram jumps the queue, in [0, 1]; needs
            ``delay_ms + jitter_ms > 0``.
        outage_s: ``(start, end)`` flight seconds with the link dead (``0 <= start < end``), or
            None.
        source: where it came from (for error messages).
    """

    SECTION: ClassVar[str] = "link"

    loss_prob: float = probability("each datagram is lost")
    delay_ms: float = _delay(f"fixed one-way delay (delay_ms + jitter_ms <= {MAX_DELAY_MS:g})")
    jitter_ms: float = _delay("extra delay drawn from U(0, jitter_ms) per datagram, in order")
    duplicate_prob: float = probability("a delivered datagram arrives twice")
    reorder_prob: float = probability(
        "a datagram jumps the queue (tc-netem reorder); needs delay_ms or jitter_ms > 0"
    )
    outage_s: tuple[float, float] | None = span(
        None,
        unit="s",
        lo=0.0,
        noun="",
        ends=("start", "end"),
        strict=True,
        finite_hi=False,
        doc="flight seconds with the link dead both ways (end = inf: for good; absent: none)",
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        where = f"{self.source}: [link]"
        if self.delay_ms + self.jitter_ms > MAX_DELAY_MS:
            raise ConfigError(
                f"{where} delay_ms + jitter_ms = {self.delay_ms + self.jitter_ms:g}; expected "
                f"at most {MAX_DELAY_MS:g} ms"
            )
        if self.reorder_prob > 0.0 and self.delay_ms + self.jitter_ms == 0.0:
            raise ConfigError(
                f"{where} reorder_prob = {self.reorder_prob} needs delay_ms or jitter_ms > 0: a "
                "reordered datagram overtakes the delayed ones (tc-netem's reorder)"
            )

    @property
    def active(self) -> bool:
        """Whether any impairment is on (an all-default section is a perfect link)."""
        return self != LinkConfig()

    def in_outage(self, flight_time_s: float | None) -> bool:
        """Whether the link is dead at ``flight_time_s`` (None: not flying, never dead)."""
        if self.outage_s is None or flight_time_s is None:
            return False
        start, end = self.outage_s
        return start <= flight_time_s < end

    def with_overrides(self, **values: float | tuple[float, float] | None) -> LinkConfig:
        """This section with the given keys replaced (None values are ignored): the
        ``visland sitl --link-*`` flags over a scenario's ``[link]``."""
        given = {k: v for k, v in values.items() if v is not None}
        unknown = sorted(set(given) - set(LINK_KEYS))
        if unknown:
            raise ConfigError(f"[link] unknown key(s) {unknown}; expected {list(LINK_KEYS)}")
        return replace(self, **given)


LINK_KEYS = section_keys(LinkConfig)


def link_config_from_table(table: Any, where: str) -> LinkConfig:
    """Check and type a scenario file's ``[link]`` table (``where`` names the file)."""
    return LinkConfig.from_table(table, where)


@dataclass
class StreamStats:
    """What one stream did to its datagrams (mutable counters).

    ``offered`` = datagrams handed to the link; ``delivered`` = released to the other end
    (duplicates included); ``lost`` = dropped by ``loss_prob``; ``outage`` = dropped while the
    link was cut; ``delayed`` = held for a delay > 0 before release; ``duplicated`` = extra
    copies made; ``reordered`` = released ahead of an earlier datagram still held.
    """

    offered: int = 0
    delivered: int = 0
    lost: int = 0
    outage: int = 0
    delayed: int = 0
    duplicated: int = 0
    reordered: int = 0

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


T = TypeVar("T")


class ImpairedStream(Generic[T]):
    """One direction of one link: decides each datagram's fate when offered, holds it until its
    release time (no clock of its own: the caller passes ``now_s``, so tests inject time).

    Args:
        config: the impairment.
        rng: this stream's generator.
        name: for the stats (``mavlink_tx``, ...).
    """

    def __init__(self, config: LinkConfig, rng: np.random.Generator, name: str = "") -> None:
        self.config = config
        self.name = name
        self.stats = StreamStats()
        self._rng = rng
        self._held: list[tuple[float, int, T]] = []  # heap of (release_s, order, datagram)
        self._order = 0
        self._tail_s = -math.inf  # release time of the newest in-order datagram

    def reseed(self, config: LinkConfig, rng: np.random.Generator) -> None:
        """A new episode: its impairment, generator and counters; datagrams already in flight
        stay in flight."""
        self.config = config
        self._rng = rng
        self.stats = StreamStats()

    @property
    def held(self) -> int:
        """Datagrams waiting for their release time."""
        return len(self._held)

    def next_release_s(self) -> float | None:
        """When the next held datagram is due (None: nothing held)."""
        return self._held[0][0] if self._held else None

    def offer(self, datagram: T, now_s: float, cut: bool = False) -> None:
        """Hand one datagram to the link at ``now_s``; ``cut``: the link is dead (outage)."""
        st = self.stats
        st.offered += 1
        cfg = self.config
        u_loss, u_dup, u_reorder, u_jitter, u_dup_jitter = self._rng.random(_DRAWS_PER_DATAGRAM)
        if cut:
            st.outage += 1
            return
        if u_loss < cfg.loss_prob:
            st.lost += 1
            return
        if u_reorder < cfg.reorder_prob:
            if self._tail_s > now_s:  # an earlier datagram is still held: this one overtakes it
                st.reordered += 1
            self._push(now_s, datagram)  # jumps the queue: released at once
        else:
            self._push_in_order(now_s, datagram, u_jitter)
        if u_dup < cfg.duplicate_prob:
            st.duplicated += 1
            self._push_in_order(now_s, datagram, u_dup_jitter)

    def _push_in_order(self, now_s: float, datagram: T, u_jitter: float) -> None:
        cfg = self.config
        release = now_s + 1e-3 * (cfg.delay_ms + cfg.jitter_ms * float(u_jitter))
        release = max(release, self._tail_s)  # a queue: never before an earlier datagram
        self._tail_s = release
        if release > now_s:
            self.stats.delayed += 1
        self._push(release, datagram)

    def _push(self, release_s: float, datagram: T) -> None:
        heapq.heappush(self._held, (release_s, self._order, datagram))
        self._order += 1

    def due(self, now_s: float) -> list[T]:
        """The datagrams whose release time has come, in release order."""
        out: list[T] = []
        held = self._held
        while held and held[0][0] <= now_s:
            out.append(heapq.heappop(held)[2])
        self.stats.delivered += len(out)
        return out


class LinkImpairment:
    """The SITL's impaired link: one :class:`ImpairedStream` per entry of :data:`STREAMS`,
    re-seeded at each episode start.

    Args:
        config: the ``[link]`` section (with any ``--link-*`` overrides applied).
        seed: the SITL's seed.
        clock: the wall clock the delays are measured on (``time.monotonic``; injectable).
    """

    def __init__(self, config: LinkConfig, seed: int, clock: Callable[[], float]) -> None:
        self.config = config
        self.seed = int(seed)
        self.clock = clock
        self.episode: int | None = None
        self.cut = False
        """The link is dead now (``outage_s``): set by the SITL at every physics step."""
        rngs = self._rngs(0)
        self.streams: dict[str, ImpairedStream[Any]] = {
            name: ImpairedStream(config, rng, name) for name, rng in zip(STREAMS, rngs, strict=True)
        }

    def _rngs(self, episode_index: int) -> list[np.random.Generator]:
        root = np.random.default_rng([self.seed, int(episode_index), LINK_STREAM])
        return root.spawn(len(STREAMS))

    def start_episode(self, index: int) -> None:
        """Episode ``index`` starts: each stream's fates restart from ``(seed, index)``."""
        self.episode = index
        for stream, rng in zip(self.streams.values(), self._rngs(index), strict=True):
            stream.reseed(self.config, rng)

    def next_release_s(self) -> float | None:
        """The earliest release time over every stream (None: nothing held)."""
        times = [t for s in self.streams.values() if (t := s.next_release_s()) is not None]
        return min(times) if times else None

    def stats(self) -> dict[str, dict[str, int]]:
        """Per-stream counters of the current episode."""
        return {name: s.stats.to_dict() for name, s in self.streams.items()}
