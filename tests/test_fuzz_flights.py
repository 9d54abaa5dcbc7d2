"""Fuzz at scale (opt-in, ``pytest -m slow``): 100,000 malformed datagrams into every UDP port of
both processes — the SITL's offboard and ground-station MAVLink ports, the companion's MAVLink
port and its camera port — while the shipped model flies lockstep landings through them.

Nothing may crash, every landing must fly as it does without the flood, and the refusals must be
counted where a user looks: the SITL's SYS_STATUS error fields (as the companion received them)
and the companion's report (``link.rx_bad_data``, ``camera.bad_packets``).
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
from training.fly import FlyConfig, fly, free_udp_port

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "models" / "visland_vision.pt"
PER_PORT = 100_000
RATE_PER_PORT = 6000  # datagrams per second and port: the flood outlasts most of the flights
EPISODES = 8


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

    def run(self) -> None:
        batch = RATE_PER_PORT // 100
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            t0 = time.monotonic()
            k = 0
            while not self.stop.is_set() and min(self.sent.values()) < PER_PORT:
                for port, pool in self.targets:
                    for i in range(batch):
                        d = pool[(k + i) % len(pool)]
                        try:
                            s.sendto(d, ("127.0.0.1", port))
                        except OSError:  # e.g. too big for loopback, or a refused port
                            self.errors += 1
                        self.sent[port] += 1
                k += batch
                # paced on the wall clock: behind schedule (a loaded machine) it just sends on
                ahead = t0 + k / RATE_PER_PORT - time.monotonic()
                if ahead > 0:
                    time.sleep(ahead)
            self.done_at = time.monotonic()


def _fly(tmp: Path, name: str, ports: tuple[int, int, int], gcs: int) -> dict:
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
            progress=False,
        )
    )


def test_a_flood_of_malformed_datagrams_on_every_port_harms_no_flight(tmp_path):
    baseline = _fly(
        tmp_path, "calm", (free_udp_port(), free_udp_port(), free_udp_port()), free_udp_port()
    )
    mav, remote, cam, gcs = (free_udp_port() for _ in range(4))
    flood = Flood([mav, gcs, remote], cam)
    flood.start()
    try:
        flooded = _fly(tmp_path, "flood", (mav, remote, cam), gcs)
        flights_done = time.monotonic()
    finally:
        flood.stop.set()
        flood.join(10)
    # the whole flood went out while the processes were flying
    assert min(flood.sent.values()) >= PER_PORT, flood.sent
    assert flood.done_at is not None and flood.done_at <= flights_done
    # every landing flew as it does without the flood (lockstep: the same frames, the same
    # answers; a lockstep wait cut short by a starved process may shift a touchdown slightly)
    assert flooded["success_rate"] == baseline["success_rate"] == 1.0
    for a, b in zip(baseline["per_episode"], flooded["per_episode"], strict=True):
        assert abs(a["landing_error_m"] - b["landing_error_m"]) <= 0.05, (a, b)
        assert abs(a["touchdown_speed_m_s"] - b["touchdown_speed_m_s"]) <= 0.1, (a, b)
    # refusals counted: the companion's report ...
    report = json.loads((tmp_path / "flood" / "companion.json").read_text())
    assert report["link"]["rx_bad_data"] > 1000, report["link"]
    assert report["link"]["rx_other_systems"] > 1000, report["link"]
    assert report["camera"]["bad_packets"] > 1000, report["camera"]
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
                "landing_error_m": [r["landing_error_m"] for r in flooded["per_episode"]],
            }
        )
    )
    assert max(m["errors_comm"] for m in status) > 1000
    assert max(m["drop_rate_comm"] for m in status) > 0
    assert max(m["errors_count2"] for m in status) > 100  # wrong-target messages
