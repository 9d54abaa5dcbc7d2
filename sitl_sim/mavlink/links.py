"""The SITL's sockets: the offboard MAVLink link, the ground-station link and the camera's UDP
socket, all through the scenario's impaired link (``[link]``, real time only) when there is one.

Everything sent is packed (and signed) once: the ground station gets the same frame as the
offboard link, as every PX4 link sees the system's one message sequence. On a perfect link the
frames sent are batched into one datagram per link until :meth:`Links.flush` (the SITL flushes
after each physics step, each poll, and before a camera frame, so telemetry stamped at a frame's
time is on the wire before the frame).
"""

from __future__ import annotations

import logging
import math
import select
import socket
import time
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Any

from companion.contract.records import EventKind
from companion.contract.signing import signing_key_bytes
from sitl_sim.errors import ConfigError
from sitl_sim.mavlink.endpoint import Inbound, LinkStats, MavlinkEndpoint, RxError, SitlError
from sitl_sim.mavlink.link_impairment import LinkConfig, LinkImpairment

if TYPE_CHECKING:
    from sitl_sim.mavlink.config import SitlConfig
    from sitl_sim.mavlink.flight_log import FlightLog
    from sitl_sim.scenario import Scenario

__all__ = ["Links", "link_impairment"]

log = logging.getLogger("visland.sitl")


class Links:
    """Bind the SITL's links (use :meth:`close` to release them).

    Args:
        config: the ports, hosts and signing key (``--signing-key``).
        impairment: the impaired link the offboard MAVLink link and the camera pass through
            (None: a perfect link; the ground-station link is never impaired).

    Raises:
        SitlPortInUseError: the MAVLink port is taken (a taken ground-station port only turns
            that link off, with a warning).
    """

    def __init__(self, config: SitlConfig, impairment: LinkImpairment | None) -> None:
        key = signing_key_bytes(config.signing_key) if config.signing_key else None
        self.offboard = MavlinkEndpoint(
            (config.host, config.mavlink_port),
            (config.remote_host, config.remote_port),
            signing_key=key,
        )
        self.gcs: MavlinkEndpoint | None = None
        """The ground-station link (None: ``gcs`` off, or its port was taken)."""
        if config.gcs:
            try:
                self.gcs = MavlinkEndpoint(
                    (config.host, config.gcs_port),
                    (config.gcs_remote_host, config.gcs_remote_port),
                    signing_key=key,
                    name="gcs",
                )
            except SitlError as exc:
                # The offboard link is the one a flight needs; a second SITL (or a PX4) holding
                # 18570 must not stop this one. Said once, loudly; --gcs-port / --no-gcs fix it.
                log.warning("ground-station link off: %s (use --gcs-port or --no-gcs)", exc)
        self.offboard.set_impairment(impairment)
        self.impairment = impairment
        self.all = [self.offboard] + ([self.gcs] if self.gcs is not None else [])
        """Every MAVLink link, the offboard one first."""
        self._fds = [e.fileno() for e in self.all]
        for endpoint in self.all:
            endpoint.batching = impairment is None
        self._camera_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._camera_addr = (config.camera_host, config.camera_port)
        self.camera_tx_errors = 0
        """Camera datagrams the socket refused (nobody listening, buffer full)."""

    @property
    def mav(self) -> Any:
        """The codec messages are built with (the offboard link's)."""
        return self.offboard.mav

    def send(self, msg: Any, component: int | None = None) -> None:
        """Pack (and sign) once; send on every link (from ``component``, None: the
        autopilot's)."""
        buf = self.offboard.send(msg, component)
        if self.gcs is not None:
            self.gcs.send_bytes(buf)

    @property
    def tx_messages(self) -> int:
        """Messages sent (or batched) on every link so far."""
        return sum(e.stats.tx_messages for e in self.all)

    def flush(self) -> None:
        """Send every link's batched frames (one datagram each)."""
        for endpoint in self.all:
            endpoint.flush()

    def send_camera(self, datagrams: Iterable[bytes]) -> None:
        """A camera frame's datagrams, through the impaired link when there is one."""
        imp = self.impairment
        for datagram in datagrams:
            if imp is None:
                self._camera_sendto(datagram)
            else:
                imp.streams["camera_tx"].offer(datagram, imp.clock(), imp.cut)

    def receive(self) -> Iterator[tuple[MavlinkEndpoint, list[Inbound], list[RxError]]]:
        """What each link received: ``(link, accepted, errors)``, the offboard link first;
        nothing at all when no datagram waits on a perfect link (one ``select`` instead of a
        read per link: most physics steps receive nothing)."""
        if self.impairment is None and not select.select(self._fds, [], [], 0)[0]:
            return
        for endpoint in self.all:
            accepted, errors = endpoint.receive()
            yield endpoint, accepted, errors

    def total_stats(self) -> LinkStats:
        """The system's counters: every link's, summed."""
        return LinkStats.total(*(e.stats for e in self.all))

    def stats_by_link(self) -> dict[str, dict[str, int]]:
        return {e.name: e.stats.to_dict() for e in self.all}

    def set_signing_key(self, key: bytes | None, initial_timestamp: int) -> None:
        """Start, change or stop (None) signing on every link at once."""
        for endpoint in self.all:
            endpoint.set_signing_key(key, initial_timestamp)

    def sleep(self, timeout_s: float) -> None:
        """Wait for a datagram (on any link), the timeout, or the impaired link's next
        release."""
        imp = self.impairment
        if imp is not None:
            due = imp.next_release_s()
            if due is not None:
                timeout_s = min(timeout_s, due - time.monotonic())
        if timeout_s > 0:
            select.select(self._fds, [], [], timeout_s)

    def readable(self) -> bool:
        """A datagram is waiting on some link, or the impaired link has one due (never
        blocks)."""
        imp = self.impairment
        if imp is not None:
            due = imp.next_release_s()
            if due is not None and due <= time.monotonic():
                return True
        return bool(select.select(self._fds, [], [], 0)[0])

    def release(self) -> None:
        """Send what the impaired link releases now (MAVLink and camera; received datagrams
        are released by the links' ``receive``)."""
        imp = self.impairment
        if imp is None:
            return
        self.offboard.release()
        for datagram in imp.streams["camera_tx"].due(imp.clock()):
            self._camera_sendto(datagram)

    def drain(self) -> None:
        """Before closing: let the impaired link deliver what it still holds for the companion
        (the disarm HEARTBEAT of the last touchdown), as a real link would after we stop."""
        imp = self.impairment
        if imp is None:
            return
        cfg = imp.config
        deadline = time.monotonic() + 1e-3 * (cfg.delay_ms + cfg.jitter_ms) + 0.01
        held = (imp.streams["mavlink_tx"], imp.streams["camera_tx"])
        while any(s.held for s in held) and (now := time.monotonic()) < deadline:
            due = min(t for s in held if (t := s.next_release_s()) is not None)
            time.sleep(min(max(due - now, 0.0), 0.01))
            self.release()

    def update_cut(self, flight_time_s: float, flying: bool, flight_log: FlightLog) -> None:
        """The impaired link's ``outage_s`` window, on flight time (none before the flight):
        cut or restored now, each change logged."""
        imp = self.impairment
        if imp is None:
            return
        cut = imp.config.in_outage(flight_time_s if flying else None)
        if cut != imp.cut:
            imp.cut = cut
            what = "cut" if cut else "restored"
            text = f"link {what} at flight time {flight_time_s:.3f} s"
            flight_log.event(EventKind.LINK_OUTAGE, text)
            log.info("link %s at flight time %.3f s (outage_s)", what, flight_time_s)

    def close(self) -> None:
        for endpoint in self.all:
            endpoint.close()
        self._camera_sock.close()

    def _camera_sendto(self, datagram: bytes) -> None:
        try:
            self._camera_sock.sendto(datagram, self._camera_addr)
        except OSError:
            self.camera_tx_errors += 1


def link_impairment(scenario: Scenario, config: SitlConfig) -> LinkImpairment | None:
    """The scenario's ``[link]`` with the ``--link-*`` flags over it; None for a perfect link.

    Raises:
        ConfigError: an impaired link in lockstep (delays are wall-clock time; a held answer
            would stop the lockstep clock instead of arriving late).
    """
    base = scenario.link or LinkConfig(source=scenario.source)
    cut = config.link_cut_at_s
    link = base.with_overrides(
        loss_prob=config.link_loss_prob,
        delay_ms=config.link_delay_ms,
        jitter_ms=config.link_jitter_ms,
        duplicate_prob=config.link_duplicate_prob,
        reorder_prob=config.link_reorder_prob,
        outage_s=None if cut is None else (cut, math.inf),
    )
    if not link.active:
        return None
    if config.lockstep:
        raise ConfigError(
            f"{scenario.source}: [link] (or --link-*) impairs a real-time link, but this SITL "
            "runs in lockstep, where a delayed answer would stop the clock instead of arriving "
            "late; run with --no-lockstep (visland fly --realtime), or drop the impairment"
        )
    return LinkImpairment(link, config.seed, time.monotonic)
