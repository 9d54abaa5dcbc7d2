"""Flight cards for ``visland sitl``: a real UDP MAVLink 2 link on loopback, pymavlink clients.

Every SITL runs in a thread (or a subprocess) that the fixtures stop even when a test fails;
every wait has a timeout; each test gets its own ports. Most flights start 5-6 m above the pad
(``low_scenario``) with rendering off, so the whole file stays within seconds.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from flights import SitlThread, fly_cascade, sitl_command, sitl_with_client
from fuzzing import mavlink_fuzz
from pymavlink.dialects.v20 import common as mavlink

from companion.contract.signing import signing_key_bytes
from companion.flightlog import read_log
from sitl_sim.autopilot.px4 import (
    FORCE_DISARM_MAGIC,
    Autopilot,
    AutopilotParams,
    FlightMode,
    MavResult,
    SetpointRejected,
    custom_mode,
    mode_from_custom,
    setpoint_from_target,
)
from sitl_sim.mavlink.config import (
    SitlConfig,
    add_sitl_arguments,
    sitl_config_from_args,
)
from sitl_sim.mavlink.endpoint import (
    RX_FOREIGN_PER_CALL,
    MavlinkEndpoint,
    SitlPortInUseError,
)
from sitl_sim.mavlink.sitl import MavlinkSitl
from sitl_sim.metrics import summarize
from tools.sitl_client import (
    HOLD_CUSTOM_MODE,
    LAND_CUSTOM_MODE,
    OFFBOARD_CUSTOM_MODE,
    ClientTimeout,
    SitlClient,
)
from training.exec.fly import free_udp_port

REPO = Path(__file__).resolve().parent.parent
ACCEPTED = int(MavResult.ACCEPTED)


# --------------------------------------------------------------------------- fixtures


@pytest.fixture
def ports() -> SimpleNamespace:
    return SimpleNamespace(
        mavlink=free_udp_port(),
        remote=free_udp_port(),
        camera=free_udp_port(),
        gcs=free_udp_port(),
        gcs_remote=free_udp_port(),
    )


@pytest.fixture
def start_sitl(ports, low_scenario, tmp_path):
    runners: list[SitlThread] = []

    def start(**overrides) -> SitlThread:
        values = dict(
            mavlink_port=ports.mavlink,
            remote_port=ports.remote,
            camera_port=ports.camera,
            gcs_port=ports.gcs,
            gcs_remote_port=ports.gcs_remote,
            scenario=low_scenario,
            log_dir=str(tmp_path / "logs"),
            render=False,
            lockstep_timeout_s=0.1,
            max_wall_s=60.0,
        )
        values.update(overrides)
        runner = SitlThread(MavlinkSitl(SitlConfig(**values)))
        runners.append(runner)
        return runner

    yield start
    for runner in runners:
        runner.stop()
    for runner in runners:
        if runner.error is not None:
            raise runner.error


@pytest.fixture
def client(ports):
    c = SitlClient(("127.0.0.1", ports.mavlink), ports.remote, ports.camera)
    yield c
    c.close()


def _hover_thrust(client: SitlClient) -> float:
    """MPC_THR_HOVER, read over the link as a companion would."""
    client.send(client.mav.param_request_read_encode(1, 1, b"MPC_THR_HOVER", -1))
    msg = client.wait_for("PARAM_VALUE", 3.0, lambda m: m.param_id == "MPC_THR_HOVER")
    return float(msg.param_value)


def _engage_offboard(client: SitlClient, thrust: float, frames: int = 3) -> None:
    """Pre-stream setpoints (answering frames), then request OFFBOARD."""
    for _ in range(frames):
        frame = client.next_frame(5.0)
        client.setpoint(thrust, (0.0, 0.0, 0.0), frame.time_us // 1000)
    assert client.set_offboard() == ACCEPTED


def _fly(client: SitlClient, frames: int, thrust: float, rates=(0.0, 0.0, 0.0)) -> None:
    for _ in range(frames):
        frame = client.next_frame(5.0)
        client.setpoint(thrust, rates, frame.time_us // 1000)


# --------------------------------------------------------------------------- autopilot units


def test_px4_custom_modes_match_the_reference_table():
    assert custom_mode(FlightMode.OFFBOARD) == 393216
    assert custom_mode(FlightMode.LAND) == 100925440
    assert custom_mode(FlightMode.HOLD) == 50593792
    assert mode_from_custom(6, 0) is FlightMode.OFFBOARD
    assert mode_from_custom(4, 9) is FlightMode.PRECLAND
    assert mode_from_custom(3, 0) is False  # POSCTL exists but needs GPS
    assert mode_from_custom(42, 0) is None


def test_type_mask_128_is_the_command_contract_and_other_masks_follow_px4():
    sp = setpoint_from_target(128, [1, 0, 0, 0], (0.1, -0.2, 0.3), 0.6, None, 1.0, None)
    cmd = sp.command()
    assert cmd.thrust_norm == 0.6 and cmd.rate_frd_rad_s.tolist() == [0.1, -0.2, 0.3]
    # yaw-rate ignored -> 0; thrust clamped to [0, 1]
    sp = setpoint_from_target(128 | 4, [1, 0, 0, 0], (0.1, 0.2, 0.3), 1.7, None, 0.0, None)
    assert sp.command().rate_frd_rad_s[2] == 0.0 and sp.thrust_norm == 1.0
    # attitude + roll/pitch rates both ignored: PX4 drops the message
    with pytest.raises(SetpointRejected, match="drops"):
        setpoint_from_target(128 | 1 | 2, [1, 0, 0, 0], (0, 0, 0), 0.5, None, 0.0, None)
    with pytest.raises(SetpointRejected, match="non-finite"):
        setpoint_from_target(128, [1, 0, 0, 0], (math.nan, 0, 0), 0.5, None, 0.0, None)
    # THROTTLE_IGNORE keeps the previous thrust; THRUST_BODY_SET uses -thrust_body z
    assert (
        setpoint_from_target(128 | 64, [1, 0, 0, 0], (0, 0, 0), 0.9, None, 0, 0.4).thrust_norm
        == 0.4
    )
    sp = setpoint_from_target(128 | 32, [1, 0, 0, 0], (0, 0, 0), 0.0, (0, 0, -0.55), 0, None)
    assert sp.thrust_norm == pytest.approx(0.55)
    # attitude branch (mask 7: rates ignored): a roll attitude error gives a positive roll rate
    half = math.radians(10) / 2
    sp = setpoint_from_target(
        7, [math.cos(half), math.sin(half), 0, 0], (0, 0, 0), 0.5, None, 0, None
    )
    rates = sp.command(np.array([1.0, 0.0, 0.0, 0.0])).rate_frd_rad_s
    assert rates[0] > 0.5 and abs(rates[1]) < 1e-9
    with pytest.raises(SetpointRejected, match="rotation"):
        setpoint_from_target(0, [0, 0, 0, 0], (0, 0, 0), 0.5, None, 0, None)


def test_autopilot_offboard_rules_failsafe_and_auto_disarm():
    ap = Autopilot(AutopilotParams())
    assert ap.request_mode(FlightMode.OFFBOARD, 0.0) is MavResult.TEMPORARILY_REJECTED
    ap.on_setpoint(setpoint_from_target(128, [1, 0, 0, 0], (0, 0, 0), 0.5, None, 0.0, None))
    assert ap.request_mode(FlightMode.OFFBOARD, 0.5) is MavResult.ACCEPTED
    assert ap.taken_over and ap.physics_running
    ap.update(1.0, on_ground=False)
    assert ap.mode is FlightMode.OFFBOARD  # 1.0 s of silence is still within COM_OF_LOSS_T
    ap.update(1.1, on_ground=False)
    assert ap.mode is FlightMode.LAND
    assert any(e.kind == "failsafe" for e in ap.pop_events())
    assert ap.request_arm(False, force=False, in_air=True) is MavResult.DENIED
    ap.update(5.0, on_ground=True)
    ap.update(6.9, on_ground=True)
    assert ap.armed
    ap.update(7.0, on_ground=True)
    assert not ap.armed


# --------------------------------------------------------------------------- flight cards


def test_heartbeat_is_px4_quadrotor_and_a_mode_change_shows_in_the_next_one(start_sitl, client):
    start_sitl()
    hb = client.wait_for("HEARTBEAT", 5.0)
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.custom_mode == HOLD_CUSTOM_MODE and hb.base_mode == 157  # armed, auto
    assert hb.get_msgbuf()[0] == mavlink.PROTOCOL_MARKER_V2  # MAVLink 2 on the wire
    hover = _hover_thrust(client)
    for _ in range(3):
        frame = client.next_frame(5.0)
        client.setpoint(hover, (0, 0, 0), frame.time_us // 1000)
    client.inbox.clear()
    client.send(
        client.mav.command_long_encode(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0)
    )
    seen = []
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline and not any(m.get_type() == "HEARTBEAT" for m in seen):
        client.poll(0.05)
        seen.extend(client.inbox)
        client.inbox.clear()
    names = [m.get_type() for m in seen]
    ack = next(m for m in seen if m.get_type() == "COMMAND_ACK")
    assert ack.result == ACCEPTED and ack.target_system == 255 and ack.target_component == 190
    first_hb = next(m for m in seen if m.get_type() == "HEARTBEAT")
    assert first_hb.custom_mode == OFFBOARD_CUSTOM_MODE
    # the heartbeat was sent at once, not at the next 1 Hz slot
    assert names.index("HEARTBEAT") <= names.index("COMMAND_ACK") + 3


def test_offboard_is_refused_without_a_setpoint_stream(start_sitl, client):
    start_sitl()
    client.wait_for("HEARTBEAT", 5.0)
    assert client.set_offboard() == int(MavResult.TEMPORARILY_REJECTED)
    hb = client.wait_for("HEARTBEAT", 3.0)
    assert hb.custom_mode == HOLD_CUSTOM_MODE


def test_hold_freezes_the_vehicle_at_its_initial_state(start_sitl, client):
    runner = start_sitl(groundtruth=True)
    first = client.wait_for("ODOMETRY", 5.0)
    later = client.wait_for("ODOMETRY", 3.0, lambda m: m.time_usec >= first.time_usec + 500_000)
    assert (first.x, first.y, first.z, list(first.q)) == (later.x, later.y, later.z, list(later.q))
    imu = client.wait_for("HIGHRES_IMU", 2.0)
    assert imu.zacc == pytest.approx(-9.81, abs=0.5) and imu.fields_updated == 0b111111
    init = runner.sitl.sampler.sample(0)
    assert (first.x, first.y) == pytest.approx(init.pos_ned_m[:2], abs=1e-5)


@pytest.mark.parametrize(("axis", "field"), [(0, "roll"), (1, "pitch")])
def test_positive_body_rate_grows_that_attitude_angle(start_sitl, client, axis, field):
    start_sitl()
    client.wait_for("HEARTBEAT", 5.0)
    hover = _hover_thrust(client)
    _engage_offboard(client, hover)
    _fly(client, 1, hover)
    before = getattr(client.wait_for("ATTITUDE", 2.0), field)
    rates = [0.0, 0.0, 0.0]
    rates[axis] = 0.4
    _fly(client, 10, hover, rates)  # 1 s at 0.4 rad/s
    after = getattr(client.wait_for("ATTITUDE", 2.0), field)
    assert after - before > 0.25, (before, after)


def test_thrust_above_hover_climbs_on_the_radar(start_sitl, client):
    start_sitl()
    client.wait_for("HEARTBEAT", 5.0)
    hover = _hover_thrust(client)
    _engage_offboard(client, hover)
    _fly(client, 1, hover)
    ds = client.wait_for("DISTANCE_SENSOR", 2.0)
    assert ds.type == mavlink.MAV_DISTANCE_SENSOR_RADAR and ds.orientation == 25
    assert ds.min_distance == 0 and ds.max_distance == 15000
    before = ds.current_distance
    _fly(client, 15, min(1.0, hover + 0.2))
    after = client.wait_for("DISTANCE_SENSOR", 2.0).current_distance
    assert after - before > 50, (before, after)  # cm


def test_setpoint_silence_fails_safe_to_land_and_touches_down_softly(start_sitl, client):
    runner = start_sitl(lockstep_timeout_s=0.05)
    client.wait_for("HEARTBEAT", 5.0)
    hover = _hover_thrust(client)
    _engage_offboard(client, hover)
    _fly(client, 5, hover)
    # silence: keep listening, send nothing
    hb = client.wait_for("HEARTBEAT", 10.0, lambda m: m.custom_mode == LAND_CUSTOM_MODE)
    assert hb.base_mode & 128  # still armed
    assert any("Failsafe" in t for t in client.statustexts)
    results = runner.finish(30.0)
    assert len(results) == 1 and results[0].landed
    assert results[0].touchdown_vertical_speed_m_s <= 1.0
    flight = read_log(Path(runner.sitl.config.log_dir) / "sitl_seed0_ep0000.mcap")
    last_sp = flight.topic("/mavlink/in/SET_ATTITUDE_TARGET")[-1]["time_s"]
    failsafe = next(e for e in flight.topic("/events") if e["kind"] == "failsafe")["time_s"]
    assert 1.0 < failsafe - last_sp <= 1.1 + 1e-6  # COM_OF_LOSS_T + PX4's 10 Hz check


def _flight_record(log_path: Path) -> tuple[list[tuple], list[tuple]]:
    """(ground truth rows, ATTITUDE readings) of the flight part of one log."""
    flight = read_log(log_path)
    truth = [
        (r["flight_time_s"], tuple(r["pos_ned_m"]), tuple(r["vel_ned_m_s"]), tuple(r["quat_wxyz"]))
        for r in flight.topic("/groundtruth/state")
        if r["flying"]
    ]
    start = next(e["time_s"] for e in flight.topic("/events") if e["kind"] == "flight")
    attitude = [
        (m["roll"], m["pitch"], m["yaw"], m["rollspeed"])
        for m in flight.topic("/mavlink/out/ATTITUDE")
        if m["time_s"] >= start
    ]
    return truth, attitude


def test_lockstep_is_deterministic_for_the_same_seed_and_commands(
    low_scenario, loopback_sitl, tmp_path
):
    """Same seed, same pilot: the same flight bit for bit — ground truth and noisy sensors —
    although the second client answers each frame after a random delay (lockstep waits)."""
    runs = []
    for k in range(2):
        log_dir = tmp_path / f"run{k}"
        p, cfg = loopback_sitl(low_scenario, log_dir, groundtruth=True, seed=3)
        with sitl_with_client(p, cfg) as (c, runner):
            fly_cascade(c, runner, max_delay_s=0.02 * k)
            results = runner.finish(30.0)
        assert results[0].landed and runner.sitl.lockstep_timeouts == 0
        runs.append(_flight_record(log_dir / "sitl_seed3_ep0000.mcap"))
    assert len(runs[0][0]) > 50 and len(runs[0][1]) > 250
    assert runs[0][0] == runs[1][0]  # ground truth, bit for bit
    assert runs[0][1] == runs[1][1]  # sensor noise too


def test_signing_rejects_unsigned_and_wrongly_signed_setpoints(ports, start_sitl):
    runner = start_sitl(signing_key="testpass")
    key = signing_key_bytes("testpass")
    with SitlClient(("127.0.0.1", ports.mavlink), ports.remote, ports.camera) as c:
        hb = c.wait_for("HEARTBEAT", 5.0)
        assert hb.get_msgbuf()[2] & mavlink.MAVLINK_IFLAG_SIGNED  # the SITL signs what it sends
        stats = runner.sitl.stats
        for _ in range(5):
            c.setpoint(0.5)
        with pytest.raises(ClientTimeout):
            c.set_offboard(timeout_s=0.5)  # an unsigned command is dropped: no ACK at all
        deadline = time.monotonic() + 2
        while stats.rx_unsigned_rejected < 6 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert stats.rx_unsigned_rejected >= 6 and runner.sitl.autopilot.setpoint is None
    with SitlClient(
        ("127.0.0.1", ports.mavlink), ports.remote, ports.camera, signing_key=b"\x01" * 32
    ) as wrong:
        wrong.setpoint(0.5)
        deadline = time.monotonic() + 2
        while stats.rx_bad_signature < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert stats.rx_bad_signature >= 1 and runner.sitl.autopilot.setpoint is None
    with SitlClient(
        ("127.0.0.1", ports.mavlink), ports.remote, ports.camera, signing_key=key
    ) as good:
        for _ in range(3):
            frame = good.next_frame(5.0)
            good.setpoint(0.5, (0, 0, 0), frame.time_us // 1000)
        assert good.set_offboard() == ACCEPTED
        status = good.wait_for("SYS_STATUS", 3.0)
        assert status.errors_count1 >= 7  # signing rejections are visible over the link


def test_setup_signing_sets_changes_and_clears_the_key_only_while_disarmed(ports, start_sitl):
    runner = start_sitl(start_armed=False)
    signed_flag = mavlink.MAVLINK_IFLAG_SIGNED
    key = signing_key_bytes("provisioned over the link")
    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    with SitlClient(("127.0.0.1", ports.mavlink), ports.remote) as plain:
        hb = plain.wait_for("HEARTBEAT", 5.0)
        assert not hb.get_msgbuf()[2] & signed_flag and not hb.base_mode & 128
        plain.send(plain.mav.setup_signing_encode(1, 1, list(key), 0))  # none set: accepted
        plain.wait_for("STATUSTEXT", 3.0, lambda m: m.text == "Signing on")
        assert plain.wait_for("HEARTBEAT", 3.0).get_msgbuf()[2] & signed_flag
        with pytest.raises(ClientTimeout):  # unsigned from now on: dropped, no ACK
            plain.command_long(arm, 1, timeout_s=0.5)
    with SitlClient(("127.0.0.1", ports.mavlink), ports.remote, signing_key=key) as good:
        assert good.command_long(arm, 1) == ACCEPTED  # armed (still frozen in HOLD)
        good.send(good.mav.setup_signing_encode(1, 1, [0] * 32, 0))
        good.wait_for("STATUSTEXT", 3.0, lambda m: m.text == "SETUP_SIGNING refused: armed")
        assert runner.sitl.endpoint.signing
        assert good.command_long(arm, 0, FORCE_DISARM_MAGIC) == ACCEPTED
        good.send(good.mav.setup_signing_encode(1, 1, [0] * 32, 0))  # all zeros: off
        good.wait_for("STATUSTEXT", 3.0, lambda m: m.text == "Signing off")
    with SitlClient(("127.0.0.1", ports.mavlink), ports.remote) as plain:
        assert not plain.wait_for("HEARTBEAT", 3.0).get_msgbuf()[2] & signed_flag
        assert plain.command_long(arm, 1) == ACCEPTED
    assert not runner.sitl.gcs_endpoint.signing  # every link follows
    runner.stop()
    flight = read_log(Path(runner.sitl.config.log_dir) / "sitl_seed0_ep0000.mcap")
    setups = flight.topic("/mavlink/in/SETUP_SIGNING")
    assert len(setups) == 3 and all(m["secret_key"] == "<redacted>" for m in setups)


def test_fuzzing_never_crashes_or_stalls_a_flight(ports, start_sitl, client):
    # 1 s lockstep wait (not the fixture's 0.1 s): a loaded machine may park the client thread
    # for a while, but only a stalled SITL (the decoder's 20 ms time box failing under the flood)
    # leaves a frame unanswered for a whole second
    runner = start_sitl(groundtruth=True, lockstep_timeout_s=1.0)
    stop = threading.Event()
    sent = [0]

    def fuzz() -> None:
        rng = np.random.default_rng(7)
        mav = mavlink.MAVLink(None, srcSystem=66, srcComponent=66)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            while not stop.is_set():
                for _ in range(20):  # about 4000 datagrams per second
                    for d in mavlink_fuzz(rng, mav):
                        s.sendto(d, ("127.0.0.1", ports.mavlink))
                        sent[0] += 1
                time.sleep(0.005)

    fuzzer = threading.Thread(target=fuzz, daemon=True)
    fuzzer.start()
    try:
        # the flight starts under a fuzz already 2500 datagrams deep, however slowly a loaded
        # machine runs the fuzzer thread
        deadline = time.monotonic() + 60.0
        while sent[0] < 2500 and time.monotonic() < deadline:
            time.sleep(0.01)
        t0 = time.monotonic()
        fly_cascade(client, runner)
        results = runner.finish(30.0)
        wall = time.monotonic() - t0
    finally:
        stop.set()
        fuzzer.join(5)
    assert sent[0] > 2000
    assert results[0].landed and results[0].success
    stats = runner.sitl.stats
    assert stats.rx_bad_data > 100 and stats.rx_truncated > 100 and stats.rx_wrong_target > 100
    assert stats.rx_rejected_setpoints > 10
    status = client.last["SYS_STATUS"]
    assert status.errors_comm > 0 and status.drop_rate_comm > 0
    # the wall bound only catches a hang (the flight is ~10 s of sim time, flown in lockstep)
    assert runner.sitl.lockstep_timeouts <= 2 and wall < 60.0


def test_sigkilled_sitl_leaves_a_log_readable_up_to_a_second_before(ports, low_scenario, tmp_path):
    log_dir = tmp_path / "killed"
    cmd = sitl_command(
        ports, log_dir, "--scenario", low_scenario, "--no-render", "--no-lockstep", max_wall_s=60
    )
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        with SitlClient(("127.0.0.1", ports.mavlink), ports.remote) as c:
            c.wait_for("HEARTBEAT", 30.0)
            c.wait_for("ATTITUDE", 5.0, lambda m: m.time_boot_ms >= 2500)
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)
            c.poll(0.2)
            last_ms = c.last["ATTITUDE"].time_boot_ms
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    flight = read_log(log_dir / "sitl_seed0_ep0000.mcap")
    assert flight.truncated  # no footer: it was killed
    logged = max(m["time_s"] for m in flight.topic("/mavlink/out/ATTITUDE"))
    # at most the last second is lost (the writer flushes every second), give or take one
    # 50 Hz ATTITUDE period and the 4 ms loop step
    assert logged >= last_ms / 1000 - 1.0 - 0.03, (logged, last_ms)
    assert flight.metadata["config"]["sitl"]["mavlink_port"] == ports.mavlink


def test_a_taken_port_is_a_clear_typed_error(ports, low_scenario):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", ports.mavlink))
        cfg = SitlConfig(
            mavlink_port=ports.mavlink, gcs_port=ports.gcs, scenario=low_scenario, log_dir=None
        )
        with pytest.raises(SitlPortInUseError, match="already in use"):
            MavlinkSitl(cfg)


def test_ground_station_link_watches_and_commands_but_never_paces_lockstep(
    ports, start_sitl, client
):
    """PX4's second link: a ground station on :18570 -> :14550 sees what the companion sees and
    may command the vehicle while the companion flies on the offboard link."""
    runner = start_sitl(lockstep_timeout_s=0.2)
    sitl = runner.sitl
    with SitlClient(("127.0.0.1", ports.gcs), ports.gcs_remote, sysid=254) as gcs:
        hb = gcs.wait_for("HEARTBEAT", 5.0)
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR and hb.custom_mode == HOLD_CUSTOM_MODE
        assert gcs.wait_for("ATTITUDE", 2.0).time_boot_ms > 0
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"COM_OF_LOSS_T", -1))
        param = gcs.wait_for("PARAM_VALUE", 3.0, lambda m: m.param_id == "COM_OF_LOSS_T")
        assert param.param_value == 1.0
        client.wait_for("HEARTBEAT", 5.0)
        hover = _hover_thrust(client)
        _engage_offboard(client, hover)
        _fly(client, 3, hover)
        gcs.wait_for("HEARTBEAT", 3.0, lambda m: m.custom_mode == OFFBOARD_CUSTOM_MODE)
        assert sitl.lockstep_timeouts == 0
        # The companion goes quiet; the ground station streams setpoints stamped far ahead.
        # They count as offboard proof of life (no failsafe) but answer no camera frame, so
        # every frame waits out lockstep_timeout_s: pacing belongs to the offboard link.
        # Counted in frames, not wall time, so a loaded machine cannot change the outcome: the
        # ground station streams until the SITL has waited out three frames.
        sent, deadline = 0, time.monotonic() + 30.0
        while (sent < 50 or sitl.lockstep_timeouts < 3) and time.monotonic() < deadline:
            gcs.setpoint(hover, (0.0, 0.0, 0.0), 2**31)
            sent += 1
            time.sleep(0.02)
        assert sitl.lockstep_timeouts >= 3
        assert sitl.autopilot.mode is FlightMode.OFFBOARD  # proof of life: no failsafe
        assert gcs.command_long(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
        assert gcs.last["COMMAND_ACK"].target_system == 254  # answered to the ground station
        client.wait_for("HEARTBEAT", 3.0, lambda m: m.custom_mode == LAND_CUSTOM_MODE)
    results = runner.finish(30.0)
    assert results[0].landed
    flight = read_log(Path(sitl.config.log_dir) / "sitl_seed0_ep0000.mcap")
    commands = flight.topic("/mavlink/in/COMMAND_LONG")
    assert {m["link"] for m in commands} == {"offboard", "gcs"}
    land = next(m for m in commands if m["command"] == mavlink.MAV_CMD_NAV_LAND)
    assert land["link"] == "gcs" and land["src_system"] == 254
    assert flight.topic("/episode/result")[0]["gcs_link_stats"]["rx_messages"] >= sent


def test_ground_station_link_can_be_turned_off_and_a_taken_port_only_warns(
    ports, low_scenario, caplog
):
    parser = argparse.ArgumentParser()
    add_sitl_arguments(parser)
    cfg = sitl_config_from_args(
        parser.parse_args(
            ["--mavlink-port", str(ports.mavlink), "--scenario", low_scenario, "--no-gcs"]
        )
    )
    assert cfg.gcs is False
    with MavlinkSitl(replace(cfg, log_dir=None)) as sitl:
        assert sitl.gcs_endpoint is None and sitl.gcs_stats is None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", ports.gcs))
        cfg = replace(cfg, gcs=True, gcs_port=ports.gcs, log_dir=None)
        with caplog.at_level("WARNING", logger="visland.sitl"), MavlinkSitl(cfg) as sitl:
            assert sitl.gcs_endpoint is None  # the flight does not need it: warn, fly on
            assert sitl.endpoint.address == ("127.0.0.1", ports.mavlink)
    assert "ground-station link off" in caplog.text and "--gcs-port" in caplog.text


class _ProcessOutput:
    """Collects a subprocess's stdout lines on a thread; ``wait_for`` has a timeout."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for raw in proc.stdout:
            with self._cond:
                self.lines.append(raw.decode(errors="replace").rstrip())
                self._cond.notify_all()

    def wait_for(self, text: str, timeout_s: float) -> None:
        with self._cond:
            ok = self._cond.wait_for(lambda: any(text in line for line in self.lines), timeout_s)
        if not ok:
            raise AssertionError(f"no {text!r} within {timeout_s} s; output: {self.lines[-20:]}")


def test_mavproxy_watches_and_commands_over_the_ground_station_link(start_sitl, ports, tmp_path):
    """MAVProxy, headless, on the GCS link: it detects a PX4 vehicle, shows its mode, and a
    DO_SET_MODE AUTO.LAND typed at its prompt lands it (ACK, mode, disarm all seen by MAVProxy).

    MAVProxy's own dependencies pull opencv and vtk; its core needs only pymavlink and pyserial,
    so ``make setup`` installs it with ``--no-deps`` (pyserial is in the ``dev`` extra). (Its
    ``mode LAND`` command cannot set a PX4 mode with pymavlink 2.4.50 — it hands mavutil the
    mode-map tuple — hence ``long``.)"""
    if importlib.util.find_spec("MAVProxy") is None:  # make setup installs it (Makefile)
        pytest.fail("MAVProxy is not installed: run `make setup` (pip install --no-deps MAVProxy)")
    runner = start_sitl()
    cmd = [
        sys.executable,
        "-m",
        "MAVProxy.mavproxy",
        f"--master=udpin:127.0.0.1:{ports.gcs_remote}",
        "--no-state",
        "--mav20",
        "--default-modules=mode,cmdlong",
    ]
    env = {**os.environ, "MAVLINK20": "1"}
    proc = subprocess.Popen(
        cmd,
        cwd=tmp_path,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        out = _ProcessOutput(proc)
        out.wait_for("Detected vehicle 1:1", 30.0)
        out.wait_for("Mode LOITER", 10.0)  # PX4 AUTO.LOITER = our HOLD
        assert proc.stdin is not None
        proc.stdin.write(b"long DO_SET_MODE 1 4 6\n")  # custom mode: main 4 AUTO, sub 6 LAND
        proc.stdin.flush()
        out.wait_for("DO_SET_MODE: ACCEPTED", 10.0)
        out.wait_for("AP: mode AUTO.LAND", 10.0)  # our STATUSTEXT, relayed
        out.wait_for("DISARMED", 30.0)
        results = runner.finish(30.0)
    finally:
        proc.kill()
        proc.wait(10)
    assert results[0].landed and runner.sitl.gcs_stats.rx_messages > 0


def test_params_commands_intervals_timesync(start_sitl, client):
    runner = start_sitl()
    client.wait_for("HEARTBEAT", 5.0)
    client.inbox.clear()
    client.send(client.mav.param_request_list_encode(1, 1))
    values = {}
    while len(values) < 17:
        m = client.wait_for("PARAM_VALUE", 3.0, fresh=False)
        values[m.param_id] = m
    assert m.param_count == 17  # COM_*, MPC_THR_HOVER, MAV_SYS_ID, PLD_*, LTEST_*, RTL_PLD_MD
    assert values["PLD_BTOUT"].param_value == 5.0
    assert np.float32(values["PLD_MAX_SRCH"].param_value).view(np.int32) == 3  # byte-wise
    assert values["COM_OF_LOSS_T"].param_value == 1.0
    assert values["COM_DISARM_LAND"].param_value == 2.0
    assert values["COM_OBL_RC_ACT"].param_type == mavlink.MAV_PARAM_TYPE_INT32
    assert np.float32(values["COM_OBL_RC_ACT"].param_value).view(np.int32) == 4  # byte-wise
    assert 0.2 < values["MPC_THR_HOVER"].param_value < 0.8
    assert client.command_long(31_337) == int(MavResult.UNSUPPORTED)
    with pytest.raises(ClientTimeout):  # addressed to system 42: ignored, counted
        client.command_long(mavlink.MAV_CMD_NAV_LAND, target=(42, 1), timeout_s=0.3)
    assert runner.sitl.stats.rx_wrong_target >= 1
    # SET_MESSAGE_INTERVAL: ATTITUDE to 10 Hz
    assert (
        client.command_long(
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000
        )
        == ACCEPTED
    )
    first = client.wait_for("ATTITUDE", 2.0)
    stamps = [first.time_boot_ms]
    while stamps[-1] - stamps[0] < 1000:
        stamps.append(client.wait_for("ATTITUDE", 2.0).time_boot_ms)
    assert set(np.diff(stamps).tolist()) == {100}
    assert (
        client.command_long(
            mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
        )
        == ACCEPTED
    )
    assert client.counts["AUTOPILOT_VERSION"] >= 1 or client.wait_for("AUTOPILOT_VERSION", 2.0)
    client.send(client.mav.timesync_encode(0, 123_456))
    ts = client.wait_for("TIMESYNC", 2.0, lambda m: m.ts1 == 123_456)
    now_ms = client.wait_for("SYSTEM_TIME", 2.0).time_boot_ms
    assert abs(ts.tc1 / 1e6 - now_ms) < 1500  # sim clock, ns


def test_land_requests_fly_consecutive_episodes_each_with_its_log(start_sitl, client):
    """Episode 0 lands on COMMAND_LONG NAV_LAND, 1 on COMMAND_INT DO_SET_MODE AUTO.LAND, 2 on
    the legacy SET_MODE; each touches down, auto-disarms and gets its own flight log."""
    runner = start_sitl(episodes=3)
    for episode in range(3):
        client.wait_for(
            "HEARTBEAT", 5.0, lambda m: m.custom_mode == HOLD_CUSTOM_MODE and m.base_mode & 128
        )
        mav = client.mav
        if episode == 0:
            assert client.command_long(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
        elif episode == 1:
            client.inbox.clear()
            cmd = mavlink.MAV_CMD_DO_SET_MODE
            client.send(mav.command_int_encode(1, 1, 0, cmd, 0, 0, 1, 4, 6, 0, 0, 0, 0.0))
            ack = client.wait_for("COMMAND_ACK", 3.0, fresh=False)
            assert ack.command == mavlink.MAV_CMD_DO_SET_MODE and ack.result == ACCEPTED
        else:
            client.inbox.clear()
            client.send(mav.set_mode_encode(1, 157, LAND_CUSTOM_MODE))
        client.wait_for("HEARTBEAT", 3.0, lambda m: m.custom_mode == LAND_CUSTOM_MODE, fresh=False)
        client.wait_for(
            "EXTENDED_SYS_STATE",
            20.0,
            lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND,
            fresh=False,
        )
        client.wait_for("HEARTBEAT", 20.0, lambda m: not m.base_mode & 128, fresh=False)
    results = runner.finish(30.0)
    assert [r.landed for r in results] == [True, True, True]
    assert all(r.touchdown_vertical_speed_m_s <= 1.0 for r in results)
    assert len({r.landing_error_m for r in results}) == 3  # three different initial states
    log_dir = Path(runner.sitl.config.log_dir)
    assert sorted(p.name for p in log_dir.iterdir()) == [
        f"sitl_seed0_ep{i:04d}.mcap" for i in range(3)
    ]
    # AUTO.LAND lands where it was engaged (here the frozen initial state), as PX4's: it does
    # not know where the pad is, so a failsafe landing is no landing on the pad
    for i, r in enumerate(results):
        flight = read_log(log_dir / f"sitl_seed0_ep{i:04d}.mcap")
        engaged = np.array(flight.topic("/episode/scenario")[0]["initial_state"]["pos_ned_m"])
        touchdown = np.array(flight.topic("/groundtruth/state")[-1]["pos_ned_m"])
        assert np.hypot(*(touchdown - engaged)[:2]) < 0.05, (engaged, touchdown)
        assert abs(r.landing_error_m - np.hypot(*engaged[:2])) < 0.05, r


def test_rendered_flight_log_has_every_record(start_sitl, client):
    runner = start_sitl(render=True, groundtruth=True)
    fly_cascade(client, runner)
    results = runner.finish(30.0)
    assert results[0].success
    flight = read_log(Path(runner.sitl.config.log_dir) / "sitl_seed0_ep0000.mcap")
    assert not flight.truncated
    for topic in (
        "/groundtruth/state",
        "/groundtruth/pose",
        "/camera/image",
        "/mavlink/in/SET_ATTITUDE_TARGET",
        "/mavlink/in/COMMAND_LONG",
        "/mavlink/out/HEARTBEAT",
        "/mavlink/out/ATTITUDE",
        "/mavlink/out/ODOMETRY",
        "/episode/scenario",
        "/episode/result",
        "/autopilot/command",
    ):
        assert flight.topic(topic), topic
    _, frames = flight.images()
    assert len(frames) == len(flight.topic("/groundtruth/state")) >= client.frames_received
    assert frames[-1].std() > 1.0  # a rendered picture, not a black frame
    assert flight.topic("/episode/result")[0]["success"]
    assert flight.metadata["config"]["sitl"]["groundtruth"] is True
    assert flight.metadata["config"]["vehicle"]["mass_kg"] > 0


def test_real_time_mode_follows_the_wall_clock(start_sitl, client):
    runner = start_sitl(lockstep=False, speed=2.0)
    first = client.wait_for("SYSTEM_TIME", 5.0)
    t0 = time.monotonic()
    last = client.wait_for(
        "SYSTEM_TIME", 10.0, lambda m: m.time_boot_ms >= first.time_boot_ms + 6000
    )
    wall = time.monotonic() - t0
    sim = (last.time_boot_ms - first.time_boot_ms) / 1000
    # 3 s of wall time, so the two receipt times' scheduling delays (tens of ms on a loaded
    # 2-core machine) stay far inside the 30 %; a SITL that could not keep up says so (it
    # re-anchors its pacing after a 0.5 s overrun and counts it) and may then run slower.
    assert sim / wall <= 2.0 * 1.3
    if runner.sitl.pacing_overruns == 0:
        assert sim / wall >= 2.0 * 0.7


def test_a_stock_mavutil_client_sees_a_px4_vehicle(start_sitl, ports, monkeypatch):
    # mavutil picks MAVLink 1/2 and the dialect from the environment at import time; import it
    # here under MAVLink 2 and forget it afterwards, so that no later test inherits this choice.
    already = "pymavlink.mavutil" in sys.modules
    monkeypatch.setenv("MAVLINK20", "1")
    monkeypatch.setenv("MAVLINK_DIALECT", "common")
    import pymavlink
    from pymavlink import mavutil

    try:
        if not mavutil.mavlink20():
            pytest.skip("mavutil was imported in MAVLink 1 mode by an earlier test")
        conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{ports.remote}", source_system=255)
        try:
            start_sitl()
            hb = conn.wait_heartbeat(timeout=5)
            assert hb is not None and conn.flightmode == "LOITER"  # PX4 AUTO.LOITER
            att = conn.recv_match(type="ATTITUDE", blocking=True, timeout=3)
            assert att is not None and abs(att.roll) < 0.1
        finally:
            conn.close()
    finally:
        if not already:
            sys.modules.pop("pymavlink.mavutil", None)
            if hasattr(pymavlink, "mavutil"):
                delattr(pymavlink, "mavutil")


def test_mavsdk_connects_arms_and_runs_offboard(start_sitl, ports):
    pytest.importorskip("mavsdk.asyncio", reason="mavsdk (4.x native) not installed")
    import asyncio

    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard import OffboardAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from mavsdk.plugins.action import ActionResult
    from mavsdk.plugins.offboard import AttitudeRate, OffboardResult
    from mavsdk.plugins.telemetry import FlightMode as MavsdkMode

    # MAVSDK stamps setpoints with its own clock and streams at 20 Hz: fly it in real time.
    runner = start_sitl(lockstep=False)

    async def until(fn, ok, timeout_s=5.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            value = await fn()
            if ok(value):
                return value
            await asyncio.sleep(0.05)
        raise AssertionError(f"timed out; last value {value}")

    async def card() -> None:
        cfg = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        async with Mavsdk(cfg) as m:
            await m.add_any_connection(f"udpin://127.0.0.1:{ports.remote}")
            system = await m.first_autopilot(10)
            assert system is not None
            tel, act, off = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
            att = await until(tel.attitude_euler, lambda a: math.isfinite(a.roll_deg))
            assert abs(att.roll_deg) < 5
            dist = await until(tel.distance_sensor, lambda d: math.isfinite(d.current_distance_m))
            assert 4.0 < dist.current_distance_m < 7.0
            await until(tel.flight_mode, lambda f: MavsdkMode(f) == MavsdkMode.HOLD)
            assert ActionResult(await act.arm()) == ActionResult.SUCCESS
            hover = runner.sitl.params.mpc_thr_hover
            await off.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, hover))
            assert OffboardResult(await off.start()) == OffboardResult.SUCCESS
            await until(tel.flight_mode, lambda f: MavsdkMode(f) == MavsdkMode.OFFBOARD)
            await asyncio.sleep(0.5)
            assert await off.is_active() and runner.sitl.autopilot.mode is FlightMode.OFFBOARD
            assert OffboardResult(await off.stop()) == OffboardResult.SUCCESS
            await until(tel.flight_mode, lambda f: MavsdkMode(f) == MavsdkMode.HOLD)

    asyncio.run(asyncio.wait_for(card(), 30.0))


def test_a_flood_from_elsewhere_is_shed_and_the_remote_is_read_behind_it():
    """Of a flood from another address than the link's remote, one receive decodes
    RX_FOREIGN_PER_CALL datagrams and sheds the rest unparsed (rx_shed, in errors_comm), so the
    companion's message behind the flood is read in the same call (issue 31: decoded one by
    one, the flood's backlog held every lockstep answer back for a second and more)."""
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as companion,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger,
    ):
        companion.bind(("127.0.0.1", 0))
        endpoint = MavlinkEndpoint(("127.0.0.1", free_udp_port()), companion.getsockname())
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        try:
            flood = 100
            for _ in range(flood - 1):
                stranger.sendto(b"\x00" * 8, endpoint.address)
            stranger.sendto(bytes(30_000), endpoint.address)
            companion.sendto(mav.heartbeat_encode(18, 8, 0, 0, 4).pack(mav), endpoint.address)
            # loopback: everything is queued before the call; no time box in a test
            accepted, errors = endpoint.receive(budget_s=math.inf)
            assert [(a.msg.get_type(), a.addr) for a in accepted] == [
                ("HEARTBEAT", companion.getsockname())
            ]
            stats = endpoint.stats
            assert len(errors) == stats.rx_bad_data == RX_FOREIGN_PER_CALL
            assert stats.rx_shed == flood - RX_FOREIGN_PER_CALL and stats.rx_datagrams == flood + 1
            assert stats.errors_comm == flood
        finally:
            endpoint.close()


def test_the_companions_expert_models_the_scenarios_planet(tmp_path):
    """``visland fly --policy expert`` on Mars: the companion's MPC is built for Mars (fly
    passes the scenario's ``--planet``); with Earth's gravity it hovered until the timeout."""
    from flights import LOW_INITIAL_STATE, fly_quietly

    scenario = tmp_path / "mars_low.toml"
    scenario.write_text(f'[initial_state]{LOW_INITIAL_STATE}\n[world]\nplanet = "mars"\n')
    report = fly_quietly(
        tmp_path / "fly", policy="expert", episodes=1, seed=3, scenario=str(scenario)
    )
    (row,) = report.per_episode
    assert row.success and row.landing_error_m < 0.05, row


def test_an_episode_nobody_takes_over_is_not_started_not_a_timeout(
    tmp_path, low_scenario, loopback_sitl
):
    """A client that never engages (a landing-target companion that never sees the pad): the
    episode ends at the HOLD timeout, scored ``took_over = False`` in the result and its log,
    and reports count it under ``not_started``, apart from the flights that ran out of time."""
    p, cfg = loopback_sitl(low_scenario, tmp_path / "logs", seed=6, hold_timeout_s=1.0)
    with sitl_with_client(p, cfg) as (client, runner):
        client.wait_for("HEARTBEAT", 5.0)
        results = runner.finish(30.0)
    assert len(results) == 1 and results[0].took_over is False and not results[0].landed
    s = summarize(results)
    assert (s["not_started"], s["timeouts"], s["success_rate"]) == (1, 0, 0.0)
    log = read_log(tmp_path / "logs" / "sitl_seed6_ep0000.mcap")
    assert log.messages["/episode/result"][-1]["took_over"] is False
