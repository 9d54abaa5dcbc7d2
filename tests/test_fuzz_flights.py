"""Fuzz at scale (opt-in, ``pytest -m slow``): 100,000 malformed datagrams into every UDP port of
both processes — the SITL's offboard and ground-station MAVLink ports, the companion's MAVLink
port and its camera port — while the shipped model flies lockstep landings through them.

Nothing may crash, every landing must fly as it does without the flood (or, where the kernel
dropped some of the SITL's telemetry from a full socket buffer, land as through a lossy link),
no setpoint may go back to the flood's address, and the refusals must be counted where a user
looks: the SITL's SYS_STATUS error fields (as the companion received them) and the companion's
report (``link.rx_peer_mismatch``: datagrams from other addresses than its pinned autopilot,
refused before any parse; ``camera.bad_packets``).

Run it on a busy machine too (issue 31: with two CPU hogs beside it, one flight in 24 failed
safe while the companion parsed the flood byte by byte): ``python -c "while True: pass" &``
twice, then this test.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fuzzing import camera_fuzz, mavlink_fuzz
from pymavlink.dialects.v20 import common as mavlink

from companion.flightlog import read_log
from training.exec.fly import FlyConfig, fly, free_udp_port
from training.reports import FlyReport

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "visland_vision.pt"
PER_PORT = 100_000
RATE_PER_PORT = 2000  # datagrams per second and port (50 s of flood at full speed)
EPISODES = 24  # lockstep flights outlast the flood (it ended in episode 12 of 24 here)


def _pool(make, rng: np.random.Generator, n: int) -> list[bytes]:
    """``n`` fuzz datagrams made in advance (sending, not making them, is what is timed)."""
    out: list[bytes] = []
    while len(out) < n:
        out += make(rng)
    return out[:n]


class Flood(threading.Thread):
    """Sends ``PER_PORT`` datagrams to each of ``ports``, paced, from one socket."""

    def __init__(self, mav_ports: list[int], camera_port: int) -> None:
        super().__init__(daemon=True)
        rng = np.random.default_rng(11)
        mav = mavlink.MAVLink(None, srcSystem=66, srcComponent=66)
        mav_pool = _pool(lambda r: mavlink_fuzz(r, mav), rng, 4000)
        cam_pool = _pool(camera_fuzz, rng, 1500)
        self.targets = [(p, mav_pool) for p in mav_ports] + [(camera_port, cam_pool)]
        self.sent = {p: 0 for p, _ in self.targets}
        self.errors = 0
        self.stop = threading.Event()
        self.done_at: float | None = None
        self.got: dict[str, int] = {}
        """MAVLink messages sent back to the flood's socket, by type."""
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True

    def _drain(self, s: socket.socket) -> None:
        while True:
            try:
                data = s.recv(65_535)
            except BlockingIOError:
                return
            for msg in self._parser.parse_buffer(data) or []:
                self.got[msg.get_type()] = self.got.get(msg.get_type(), 0) + 1

    def run(self) -> None:
        batch = RATE_PER_PORT // 100
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setblocking(False)
            t0 = time.monotonic()
            k = 0
            while not self.stop.is_set() and min(self.sent.values()) < PER_PORT:
                for port, pool in self.targets:
                    for i in range(batch):
                        d = pool[(k + i) % len(pool)]
                        try:
                            s.sendto(d, ("127.0.0.1", port))
                        except OSError:  # e.g. too big for loopback, a refused port, a full
                            self.errors += 1  # buffer (non-blocking: counted as sent)
                        self.sent[port] += 1
                k += batch
                self._drain(s)
                # paced on the wall clock: behind schedule (a loaded machine) it just sends on
                ahead = t0 + k / RATE_PER_PORT - time.monotonic()
                if ahead > 0:
                    time.sleep(ahead)
            self.done_at = time.monotonic()


def _fly(tmp: Path, name: str, ports: tuple[int, int, int], gcs: int) -> FlyReport:
    return fly(
        FlyConfig(
            policy=str(SHIPPED),
            episodes=EPISODES,
            out=str(tmp / name),
            ports=ports,
            # the flood thread and both processes share 2 cores: a frame answered after the
            # default 0.5 s would end lockstep for the episode (the SITL then runs free, as PX4
            # does), which measures the machine, not the input handling under test
            sitl_args=(
                "--gcs",
                "--gcs-port",
                str(gcs),
                "--gcs-remote-port",
                str(free_udp_port()),
                "--lockstep-timeout-s",
                "5",
            ),
            # the same holds for the companion's 600 ms staleness limit, which is wall time: in
            # lockstep the next frame comes when the SITL has rendered it, and with two CPU hogs
            # beside the test it once took 635 ms in the calm run (a camera_stale failsafe with
            # no flood at all); staleness has its own tests (test_flight_controller.py)
            companion_args=("--max-age-ms", "3000"),
            progress=False,
        )
    )


def _udp_receive_buffer_drops() -> int | None:
    """The kernel's count of UDP datagrams dropped on full receive buffers (Linux, all
    sockets: ``RcvbufErrors`` of /proc/net/snmp); None where there is no such file."""
    try:
        lines = [ln.split() for ln in Path("/proc/net/snmp").read_text().splitlines()]
    except OSError:
        return None
    names, values = (ln for ln in lines if ln[0] == "Udp:")
    return int(values[names.index("RcvbufErrors")])


def _telemetry_lost(log: Path) -> int:
    """ATTITUDE and DISTANCE_SENSOR samples of the SITL's streams (50 Hz, 10 Hz) missing from a
    companion flight log between the flight's first and last policy observation."""
    flight = read_log(log)
    obs = flight.messages.get("/companion/observation", [])
    if obs:
        first_ms, last_ms = (round(obs[k]["attitude_time_s"] * 1000) for k in (0, -1))
    else:  # the policy never flew (e.g. a failsafe before its first frame): the whole log
        stamps = [m["time_boot_ms"] for m in flight.messages.get("/mavlink/in/ATTITUDE", [])]
        first_ms, last_ms = (min(stamps), max(stamps)) if stamps else (0, 0)
    lost = 0
    for topic, period_ms in (("ATTITUDE", 20), ("DISTANCE_SENSOR", 100)):
        got = {m["time_boot_ms"] for m in flight.messages[f"/mavlink/in/{topic}"]}
        want = range(first_ms - first_ms % period_ms + period_ms, last_ms, period_ms)
        lost += sum(t not in got for t in want)
    return lost


def test_a_flood_of_malformed_datagrams_on_every_port_harms_no_flight(tmp_path):
    baseline = _fly(
        tmp_path, "calm", (free_udp_port(), free_udp_port(), free_udp_port()), free_udp_port()
    )
    mav, remote, cam, gcs = (free_udp_port() for _ in range(4))
    flood = Flood([mav, gcs, remote], cam)
    kernel_drops_before = _udp_receive_buffer_drops()
    flood.start()
    try:
        flooded = _fly(tmp_path, "flood", (mav, remote, cam), gcs)
        flights_done = time.monotonic()
    finally:
        flood.stop.set()
        flood.join(10)
    kernel_drops = _udp_receive_buffer_drops()
    if kernel_drops is not None and kernel_drops_before is not None:
        kernel_drops -= kernel_drops_before
    # the whole flood went out while the processes were flying
    assert min(flood.sent.values()) >= PER_PORT, flood.sent
    assert flood.done_at is not None and flood.done_at <= flights_done
    # every landing flew as it does without the flood (lockstep: the same frames, the same
    # answers) — unless the kernel dropped some of the SITL's telemetry: where the companion,
    # sharing 2 cores with the SITL and the flood, falls behind 8,000 datagrams a second (plus
    # the SITL's COMMAND_ACKs to the flood's commands), its socket's buffer fills and the kernel
    # drops flood and telemetry datagrams alike. Such a flight is a flight over a lossy link and
    # must land as one: success, touchdown <= 0.6 m/s. (Measured here: 4,213 datagrams dropped
    # by the kernel, 1-69 ATTITUDE/DISTANCE_SENSOR samples lost in each of the 12 flights the
    # flood overlapped, all 12 landed; the other 12 equal to the calm run. At 6,000 datagrams a
    # second the camera's frames were dropped too and two flights failed safe.)
    assert flooded.summary.success_rate == baseline.summary.success_rate == 1.0
    logs = sorted((tmp_path / "flood" / "companion").glob("*_f*.mcap"))
    lost = [_telemetry_lost(log) for log in logs[: len(flooded.per_episode)]]
    for a, b, n in zip(baseline.per_episode, flooded.per_episode, lost, strict=True):
        if n == 0:
            assert a.landing_error_m == b.landing_error_m, (a, b)
            assert a.touchdown_speed_m_s == b.touchdown_speed_m_s, (a, b)
        else:
            assert b.success and b.touchdown_speed_m_s <= 0.6, (b, n)
    if kernel_drops is not None:  # and only the kernel lost telemetry
        assert sum(lost) == 0 or kernel_drops > 0, (lost, kernel_drops)
    # refusals counted: the companion's report ... (how many of the 100 000 a process reads
    # depends on the machine: the kernel drops the rest from a full socket buffer; measured
    # 948-several thousand per counter, so > 100 says "counted", not "fast"). Once the
    # autopilot is pinned, the flood's datagrams are refused unparsed (rx_peer_mismatch); what
    # came before is parsed and counted as rx_bad_data / rx_other_systems, as many as the
    # flood got in before the SITL's first HEARTBEAT (none, on a fast start)
    report = json.loads((tmp_path / "flood" / "companion.json").read_text())
    assert report["link"]["rx_peer_mismatch"] > 100, report["link"]
    assert report["camera"]["bad_packets"] > 100, report["camera"]
    # the flood's socket never got a setpoint back: the udpin link answers its pinned peer only
    # (pymavlink's own udpin sends to every address that ever sent to the port)
    assert "SET_ATTITUDE_TARGET" not in flood.got, flood.got
    # ... and the SITL's SYS_STATUS, as the companion's flight logs recorded it
    status = [
        m
        for log in sorted((tmp_path / "flood" / "companion").glob("*.mcap"))
        for m in read_log(log).topic("/mavlink/in/SYS_STATUS")
    ]
    assert status, "no SYS_STATUS in the companion's logs"
    print(  # the figures of the run (pytest -s): what was sent, refused and counted where
        json.dumps(
            {
                "sent_per_port": flood.sent,
                "companion_link": report["link"],
                "companion_camera": report["camera"],
                "sitl_sys_status_max": {
                    k: max(m[k] for m in status)
                    for k in ("errors_comm", "drop_rate_comm", "errors_count1", "errors_count2")
                },
                "landing_error_m": [r.landing_error_m for r in flooded.per_episode],
                "calm_landing_error_m": [r.landing_error_m for r in baseline.per_episode],
                "telemetry_samples_lost": lost,
                "kernel_udp_receive_buffer_drops": kernel_drops,
            }
        )
    )
    assert max(m["errors_comm"] for m in status) > 1000
    assert max(m["drop_rate_comm"] for m in status) > 0
    assert max(m["errors_count2"] for m in status) > 100  # wrong-target messages
