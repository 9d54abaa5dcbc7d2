"""The SITL's ``ardupilot`` profile (ArduCopter 4.5 on the wire): unit tests in sim time (no
sockets; the GUID_TIMEOUT and climb-rate tests fly the real physics), then flight cards with
the companion's ``--autopilot ardupilot`` against the SITL's ``--autopilot ardupilot``
(lockstep, loopback, free ports)."""

from __future__ import annotations

import math
import signal
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from flights import companion_command, free_ports, sitl_command

from companion.contract.autopilots import CopterMode
from companion.flightlog import read_log
from sitl_sim.autopilot.ardupilot import ArduCopter, ModeRefused, ardupilot_params, new_autopilot
from sitl_sim.autopilot.ardupilot_params import ArduParams
from sitl_sim.autopilot.params import (
    param_table,
    param_value_msg,
    parse_param_overrides,
    with_param,
)
from sitl_sim.autopilot.px4 import Autopilot, FlightMode, MavResult, SetpointRejected
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.mavlink.config import SitlConfig
from sitl_sim.mavlink.endpoint import SitlError
from sitl_sim.physics.dynamics import euler_from_quat, quat_from_euler
from sitl_sim.scenario import InitialState
from sitl_sim.simulator import Simulator
from training.exec.fly import DEFAULT_VISION_POLICY, FlyConfig, fly
from training.reports import FlyReport

REPO = Path(__file__).resolve().parent.parent


def _copter(**ardu) -> ArduCopter:
    params = ardupilot_params(0.4)
    if ardu:
        params = replace(params, ardu=ArduParams(**ardu))
    return ArduCopter(params)


def _guided(ap: ArduCopter, now_s: float = 0.0) -> None:
    assert ap.request_mode(ap.mode_for_command(20, 0), now_s) is MavResult.ACCEPTED
    ap.pop_events()


# --------------------------------------------------------------------------- modes


def test_heartbeat_shows_arducopter_numbers_and_base_mode_per_mode():
    ap = _copter()
    # start: the frozen hold is ALT_HOLD; STABILIZE|MANUAL_INPUT|CUSTOM (81) + ARMED (128)
    assert ap.heartbeat() == (3, 209, CopterMode.ALT_HOLD, 4)  # ARDUPILOTMEGA, ACTIVE
    _guided(ap)
    assert ap.heartbeat() == (3, 209, 20, 4) and ap.mode_label == "GUIDED_NOGPS"
    assert ap.request_mode(ap.mode_for_command(9, 0), 1.0) is MavResult.ACCEPTED
    assert ap.mode is FlightMode.LAND and ap.heartbeat()[2] == 9
    ap.request_arm(False, force=False, in_air=False)
    assert ap.heartbeat() == (3, 81, 9, 3)  # disarmed: STANDBY
    # LAND with PLND_ENABLED = 1 and PLND_TYPE = 1 is the precision land, still LAND 9 on the
    # wire, + GUIDED_ENABLED (the horizontal position controller runs)
    plnd = _copter(plnd_enabled=1, plnd_type=1)
    assert plnd.mode_for_custom(9) is FlightMode.PRECLAND
    plnd.request_mode(FlightMode.PRECLAND, 0.0)
    assert plnd.heartbeat() == (3, 81 | 8 | 128, 9, 4) and plnd.mode_label == "LAND"
    assert _copter(plnd_enabled=1, plnd_type=2).land_mode() is FlightMode.LAND  # not MAVLink
    # the px4 profile is untouched
    px4 = new_autopilot("px4", ardupilot_params(0.4), armed=True)
    assert type(px4) is Autopilot and px4.heartbeat() == (12, 157, (4 << 16) | (3 << 24), 4)
    with pytest.raises(ValueError, match="expected 'px4' or 'ardupilot'"):
        new_autopilot("inav", ardupilot_params(0.4), armed=True)


def test_gps_modes_and_unknown_numbers_fail_with_arducopter_texts():
    ap = _copter()
    for number, name in ((4, "GUIDED"), (5, "LOITER"), (6, "RTL"), (3, "AUTO"), (16, "POSHOLD")):
        result = ap.request_mode(ap.mode_for_command(number, 0), 0.0)
        assert result is MavResult.FAILED
        (event,) = ap.pop_events()
        assert event.text == f"Mode change to {name} failed: requires position"
        assert event.severity == 4 and event.statustext
    assert ap.request_mode(ap.mode_for_custom(99), 0.0) is MavResult.FAILED
    assert ap.pop_events()[0].text == "No such mode 99"
    assert ap.mode_for_custom(0) == ModeRefused(
        "Mode change to STABILIZE failed: needs a pilot (not modelled)"
    )
    assert ap.mode is FlightMode.HOLD and not ap.taken_over  # nothing changed


def test_guided_nogps_needs_no_setpoint_stream_and_mode_changes_are_not_statustexts():
    ap = _copter()
    assert ap.setpoint is None
    assert ap.request_mode(ap.mode_for_command(20, 0), 5.0) is MavResult.ACCEPTED
    events = ap.pop_events()
    assert [e.kind for e in events] == ["mode", "takeover"]
    assert not events[0].statustext  # ArduPilot shows a mode change in the HEARTBEAT only
    assert ap.physics_running
    # setpoints outside GUIDED_NOGPS are ignored without a word (returns None, not an error)
    hold = _copter()
    assert hold.setpoint_from_message(128, [1, 0, 0, 0], (0, 0, 0), 0.5, None, 0.0) is None


# --------------------------------------------------------------------------- setpoints


def test_set_attitude_target_rates_quaternion_and_their_refusals():
    ap = _copter(guid_options=8)
    _guided(ap)
    # ATTITUDE_IGNORE: body rates (ArduCopter >= 4.2 set_angular_velocity), thrust is thrust
    sp = ap.setpoint_from_message(128, [0, 0, 0, 0], (0.1, -0.2, 0.3), 0.62, None, 1.0)
    assert sp.attitude_quat_wxyz is None and sp.climb_rate_up_m_s is None
    np.testing.assert_allclose(sp.rate_frd_rad_s, [0.1, -0.2, 0.3])
    assert sp.thrust_norm == pytest.approx(0.62)
    # quaternion, rates ignored (mask 7): attitude with no feed-forward
    q = quat_from_euler(0.1, 0.0, 0.5)
    sp = ap.setpoint_from_message(7, list(q), (9.0, 9.0, 9.0), 0.5, None, 1.0)
    np.testing.assert_allclose(sp.attitude_quat_wxyz, q)
    np.testing.assert_allclose(sp.rate_frd_rad_s, 0.0)
    # quaternion + all three rates (mask 0): rates are the feed-forward
    sp = ap.setpoint_from_message(0, list(q), (0.0, 0.0, 0.4), 0.5, None, 1.0)
    np.testing.assert_allclose(sp.rate_frd_rad_s, [0.0, 0.0, 0.4])
    # what ArduCopter ignores
    with pytest.raises(SetpointRejected, match="THROTTLE_IGNORE"):
        ap.setpoint_from_message(128 | 64, [1, 0, 0, 0], (0, 0, 0), 0.5, None, 1.0)
    with pytest.raises(SetpointRejected, match="not unit length"):
        ap.setpoint_from_message(7, [1.01, 0, 0, 0], (0, 0, 0), 0.5, None, 1.0)
    with pytest.raises(SetpointRejected, match="non-finite thrust"):
        ap.setpoint_from_message(128, [1, 0, 0, 0], (0, 0, 0), math.nan, None, 1.0)
    # mixed rate bits (PX4's "yaw rate ignored" 132): ignored, and guided re-initialised
    ap.on_setpoint(ap.setpoint_from_message(128, [1, 0, 0, 0], (0.1, 0, 0), 0.6, None, 2.0))
    with pytest.raises(SetpointRejected, match="some body rates ignored"):
        ap.setpoint_from_message(132, [1, 0, 0, 0], (0.1, 0.1, 0), 0.6, None, 2.5)
    assert ap.setpoint is None  # level, zero climb from 2.5 s


@pytest.mark.parametrize(
    ("thrust", "climb_m_s"), [(0.5, 0.0), (1.0, 2.5), (0.75, 1.25), (0.0, -1.5), (0.25, -0.75)]
)
def test_without_guid_options_bit_3_thrust_is_a_climb_rate_demand(thrust, climb_m_s):
    ap = _copter()  # GUID_OPTIONS = 0, ArduPilot's default; WPNAV_SPEED_UP/DN 250/150 cm/s
    _guided(ap)
    sp = ap.setpoint_from_message(128, [1, 0, 0, 0], (0, 0, 0), thrust, None, 1.0)
    assert sp.climb_rate_up_m_s == pytest.approx(climb_m_s)


def _flight():
    vehicle, sim_cfg = load_vehicle(), load_sim().noiseless()
    sim = Simulator(vehicle, sim_cfg, render=False)
    initial = InitialState((0.0, 0.0, -30.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.3), (0.0, 0.0, 0.0))
    sim.reset(initial, np.random.SeedSequence(7))
    return sim, sim_cfg


def _fly(sim, ap, until_s: float, setpoint=None, every_s: float = 0.1, record=None):
    """Physics at its rate with the autopilot's own command; ``setpoint()`` sent every
    ``every_s``; ``update`` at 10 Hz, as the SITL does."""
    dt = sim.sim.physics_dt_s
    next_sp = sim.time_s
    while sim.time_s < until_s - 1e-9:
        if setpoint is not None and sim.time_s >= next_sp - 1e-9:
            ap.on_setpoint(setpoint(sim.time_s))
            next_sp += every_s
        sim.step_physics(ap.flight_command(sim.time_s, sim.ground_truth))
        if round(sim.time_s / dt) % round(0.1 / dt) == 0:
            ap.update(sim.time_s, on_ground=False)
        if record is not None:
            record.append(sim.ground_truth())
    return sim.ground_truth()


def test_climb_rate_reading_flies_the_demanded_climb_rate_on_the_real_physics():
    sim, _ = _flight()
    ap = ArduCopter(ardupilot_params(sim.hover_thrust_norm))
    _guided(ap)

    def climb(t):  # thrust 0.75 = +1.25 m/s, rates 0 (mask 128)
        return ap.setpoint_from_message(128, [1, 0, 0, 0], (0, 0, 0), 0.75, None, t)

    gt = _fly(sim, ap, 4.0, climb)
    assert -gt.vel_ned_m_s[2] == pytest.approx(1.25, abs=0.03)
    sim.close()


def test_guid_timeout_levels_the_vehicle_and_holds_zero_climb_in_guided_nogps():
    sim, _ = _flight()
    ap = ArduCopter(ardupilot_params(sim.hover_thrust_norm))
    ap.params = replace(ap.params, ardu=ArduParams(guid_options=8))
    _guided(ap)
    hover = sim.hover_thrust_norm

    def tilt_and_sink(t):  # thrust as thrust: 5 % under hover, rolling and pitching slowly
        return ap.setpoint_from_message(128, [0, 0, 0, 0], (0.06, 0.03, 0.0), hover * 0.95, None, t)

    _fly(sim, ap, 1.5, tilt_and_sink)  # the last setpoint at t = 1.4 s
    # GUID_TIMEOUT 3 s: the last setpoint still rules at 4.35 s (it keeps rolling, sinking)
    gt = _fly(sim, ap, 4.35)
    roll0, pitch0, _ = euler_from_quat(gt.quat_wxyz)
    assert roll0 > 0.2 and pitch0 > 0.1 and gt.vel_ned_m_s[2] > 1.0
    assert not ap.guided_timed_out and ap.pop_events() == []
    _fly(sim, ap, 4.5)
    assert ap.guided_timed_out and ap.mode is FlightMode.OFFBOARD  # still GUIDED_NOGPS
    (event,) = ap.pop_events()
    assert event.kind == "guided_timeout" and not event.statustext  # ArduCopter is silent
    alt_at_level = -sim.ground_truth().pos_ned_m[2]
    gt = _fly(sim, ap, 12.0)
    roll, pitch, _ = euler_from_quat(gt.quat_wxyz)
    assert abs(roll) < math.radians(0.5) and abs(pitch) < math.radians(0.5)
    assert np.abs(gt.rate_frd_rad_s).max() < 0.01
    assert abs(gt.vel_ned_m_s[2]) < 0.02  # zero climb rate, held
    assert -gt.pos_ned_m[2] > alt_at_level - 3.0  # the sink stopped within metres: no crash
    assert sim.contact is None
    # setpoints back: followed again
    ap.on_setpoint(tilt_and_sink(sim.time_s))
    assert not ap.guided_timed_out and ap.pop_events()[0].kind == "guided"
    sim.close()


# --------------------------------------------------------------------------- checks


def test_land_detector_disarms_in_land_at_once_elsewhere_after_disarm_delay():
    ap = _copter()
    ap.request_mode(FlightMode.LAND, 0.0)
    ap.pop_events()
    ap.update(10.0, on_ground=True)
    ap.update(10.9, on_ground=True)
    assert ap.armed
    ap.update(11.0, on_ground=True)  # LAND_DETECTOR_TRIGGER_SEC = 1 s
    assert not ap.armed and ap.pop_events()[-1].text == "Disarming motors"
    guided = _copter()
    _guided(guided)
    guided.update(0.0, on_ground=True)
    guided.update(10.9, on_ground=True)
    assert guided.armed
    guided.update(11.0, on_ground=True)  # 1 s + DISARM_DELAY 10 s
    assert not guided.armed


def test_gcs_failsafe_lands_on_lost_gcs_heartbeats_only_when_enabled():
    off = _copter()  # FS_GCS_ENABLE = 0 (ArduCopter's default)
    _guided(off)
    off.on_heartbeat(255, 190, 0.0)
    off.update(30.0, on_ground=False)
    assert off.mode is FlightMode.OFFBOARD
    ap = _copter(fs_gcs_enable=1)
    _guided(ap)
    ap.on_heartbeat(1, 191, 0.0)  # the companion's heartbeat (the vehicle's sysid): no GCS
    ap.update(30.0, on_ground=False)
    assert ap.mode is FlightMode.OFFBOARD and not ap.gcs_failsafe  # never saw the GCS
    ap.on_heartbeat(255, 190, 30.0)
    ap.update(35.0, on_ground=False)  # FS_GCS_TIMEOUT 5 s: not more than 5 s yet
    assert not ap.gcs_failsafe
    ap.update(35.1, on_ground=False)
    assert ap.gcs_failsafe and ap.mode is FlightMode.LAND
    texts = [(e.text, e.statustext) for e in ap.pop_events()]
    assert ("GCS Failsafe", True) in texts
    assert ap.heartbeat()[3] == 5  # MAV_STATE_CRITICAL
    ap.on_heartbeat(255, 190, 36.0)
    ap.update(36.1, on_ground=False)
    assert not ap.gcs_failsafe and ap.mode is FlightMode.LAND  # it keeps landing
    assert ap.pop_events()[-1].text == "GCS Failsafe Cleared"


def test_landing_target_frames_arducopter_reads():
    from sitl_sim.autopilot.precland import LandingTargetRejected

    ap = _copter(plnd_enabled=1, plnd_type=1)
    ap.check_landing_target(12, 1, 20.0)  # BODY_FRD with a distance: read
    ap.check_landing_target(12, 0, 0.0)  # angles, range from the rangefinder
    with pytest.raises(LandingTargetRejected, match="Plnd: Frame not supported"):
        ap.check_landing_target(1, 1, 20.0)  # LOCAL_NED: PX4's, not ArduPilot's
    with pytest.raises(LandingTargetRejected, match="needs > 0"):
        ap.check_landing_target(12, 1, 0.0)


# --------------------------------------------------------------------------- parameters


def test_ardupilot_parameters_are_plain_floats_with_arducopter_names_and_defaults():
    from pymavlink.dialects.v20 import common as mavlink

    params = ardupilot_params(0.3924)
    table = param_table(params, 1, "ardupilot")
    rows = {name: (value, ptype) for name, value, ptype in table}
    assert [name for name, _, _ in table] == sorted(rows)
    assert rows["GUID_OPTIONS"] == (0, mavlink.MAV_PARAM_TYPE_INT32)
    assert rows["GUID_TIMEOUT"] == (3.0, mavlink.MAV_PARAM_TYPE_REAL32)
    assert rows["FS_GCS_ENABLE"][0] == 0 and rows["PLND_ENABLED"][0] == 0
    assert rows["PLND_TYPE"][0] == 0 and rows["SYSID_THISMAV"][0] == 1
    assert rows["MOT_THST_HOVER"][0] == pytest.approx(0.3924)
    assert rows["PLND_XY_DIST_MAX"][0] == 2.5 and rows["PLND_TIMEOUT"][0] == 4.0
    assert not any(name.startswith(("MPC_", "COM_", "PLD_")) for name in rows)
    mav = mavlink.MAVLink(None)
    index = [name for name, _, _ in table].index("GUID_OPTIONS")
    params8 = with_param(params, "GUID_OPTIONS", 8.0, "ardupilot")
    msg = param_value_msg(mav, param_table(params8, 1, "ardupilot"), index, "ardupilot")
    assert msg.param_value == 8.0  # a plain float (PX4 would send the int's bytes)
    assert with_param(params, "PLND_RET_MAX", 1.999, "ardupilot").pld.max_srch == 2  # +0.01
    with pytest.raises(ValueError, match=r"GUID_TIMEOUT = 9\.0; expected"):
        with_param(params, "GUID_TIMEOUT", 9.0, "ardupilot")
    with pytest.raises(KeyError):
        with_param(params, "MOT_THST_HOVER", 0.5, "ardupilot")  # read-only here


def test_sitl_param_flag_parses_and_names_what_is_wrong():
    assert parse_param_overrides("GUID_OPTIONS=8, plnd_enabled=1", "ardupilot") == [
        ("GUID_OPTIONS", 8.0),
        ("PLND_ENABLED", 1.0),
    ]
    assert SitlConfig(autopilot="ardupilot", param="GUID_OPTIONS=8").param == "GUID_OPTIONS=8"
    with pytest.raises(SitlError, match="not a writable ardupilot parameter; known: "):
        SitlConfig(autopilot="ardupilot", param="MPC_THR_HOVER=0.5")
    with pytest.raises(SitlError, match="expected NAME=VALUE"):
        SitlConfig(autopilot="ardupilot", param="GUID_OPTIONS")
    with pytest.raises(SitlError, match="expected a number"):
        SitlConfig(autopilot="ardupilot", param="GUID_OPTIONS=eight")
    with pytest.raises(SitlError, match="not a writable px4 parameter"):
        SitlConfig(param="GUID_OPTIONS=8")  # px4 is the default profile
    with pytest.raises(SitlError, match="autopilot = 'inav'"):
        SitlConfig(autopilot="inav")


# --------------------------------------------------------------------------- flights

_RELAXED = ("--max-age-ms", "3000")
"""Staleness is not what these cards test (as in tests/test_companion.py)."""
_PATIENT = ("--lockstep-timeout-s", "5")
"""Every frame's answer awaited: a descheduled companion cannot change a flight."""


def _fly_ardupilot(tmp_path, **cfg) -> FlyReport:
    """``visland fly --autopilot ardupilot`` into ``tmp_path/run``, staleness relaxed."""
    return fly(
        FlyConfig(
            autopilot="ardupilot",
            out=str(tmp_path / "run"),
            progress=False,
            companion_args=_RELAXED,
            **cfg,
        )
    )


def test_card_companion_flies_the_shipped_model_to_landings_in_guided_nogps(tmp_path):
    """``visland fly --autopilot ardupilot``: GUID_OPTIONS = 8 set on the SITL, the companion's
    ardupilot profile engages GUIDED_NOGPS and flies thrust + body rates to touchdown."""
    report = _fly_ardupilot(tmp_path, policy=DEFAULT_VISION_POLICY, episodes=2, sitl_args=_PATIENT)
    assert report.autopilot == "ardupilot" and report.episodes == 2
    assert report.summary.success_rate == 1.0, report.per_episode
    assert report.summary.landing_error_m.max <= 1.0
    assert report.companion_flights.get("landed") == 2
    for row in report.per_episode:
        flight = read_log(row.log)
        assert {m["mode"] for m in flight.topic("/autopilot/command")} == {"GUIDED_NOGPS"}
        beats = flight.topic("/mavlink/out/HEARTBEAT")
        assert {b["autopilot"] for b in beats} == {3}  # MAV_AUTOPILOT_ARDUPILOTMEGA
        assert {b["custom_mode"] for b in beats} == {2, 20}  # ALT_HOLD, then GUIDED_NOGPS
        assert any(b["custom_mode"] == 20 and b["base_mode"] == 209 for b in beats)
        params = {p["param_id"]: p["param_value"] for p in flight.topic("/mavlink/out/PARAM_VALUE")}
        assert params.get("GUID_OPTIONS") == 8.0 and "MOT_THST_HOVER" in params
        setpoints = flight.topic("/mavlink/in/SET_ATTITUDE_TARGET")
        assert setpoints and {s["type_mask"] for s in setpoints} == {128}
        result = flight.topic("/episode/result")[-1]
        assert result["link_stats"]["rx_rejected_setpoints"] == 0
        assert result["lockstep_timeouts"] == 0
        texts = [e["text"] for e in flight.topic("/events")]
        assert "Disarming motors" in texts


def test_card_guid_options_0_companion_refuses_to_engage_and_says_why(tmp_path):
    """ArduPilot's default GUID_OPTIONS = 0 reads thrust as a climb rate: the companion never
    requests GUIDED_NOGPS, and its log says which bit to set."""
    report = _fly_ardupilot(
        tmp_path,
        policy="expert",
        episodes=1,
        sitl_params=("GUID_OPTIONS=0",),  # after fly's GUID_OPTIONS=8: wins
        sitl_args=("--hold-timeout-s", "5"),  # the SITL gives up on a take-over
    )
    s = report.summary
    assert (s.success_rate, s.not_started, s.timeouts) == (0.0, 1, 0)  # never taken over
    assert report.per_episode[0].verdict() == "not_started"
    flight = read_log(report.per_episode[0].log)
    assert not flight.topic("/autopilot/command")  # never taken over: frozen in ALT_HOLD
    modes = [c for c in flight.topic("/mavlink/in/COMMAND_LONG") if c["command"] == 176]
    assert modes == []  # DO_SET_MODE never sent
    (comp_log,) = sorted((tmp_path / "run" / "companion").glob("*.mcap"))
    events = [e["text"] for e in read_log(comp_log).topic("/events")]
    assert (
        "GUID_OPTIONS = 0: set bit 8 so SET_ATTITUDE_TARGET thrust is collective thrust, not a "
        "climb rate"
    ) in events, events


def test_card_companion_killed_mid_flight_guid_timeout_levels_and_holds(procs, tmp_path):
    """SIGKILL in flight: ArduCopter stays in GUIDED_NOGPS, follows the last setpoint for
    GUID_TIMEOUT, then levels and holds zero climb rate (no crash) until the episode times out.
    After one unanswered frame the SITL stops waiting for the dead client (lockstep runs free).
    The companion restarted in the air does not take it back."""
    ports = free_ports()
    sitl_dir, comp_dir = tmp_path / "sitl", tmp_path / "companion"
    comp = procs.start(
        "companion",
        companion_command(
            ports.remote, ports.camera, comp_dir, "--autopilot", "ardupilot", *_RELAXED
        ),
    )
    sitl = procs.start(
        "sitl",
        sitl_command(
            ports,
            sitl_dir,
            *("--autopilot", "ardupilot", "--param", "GUID_OPTIONS=8"),
            *("--no-render", "--groundtruth"),
            # the restarted companion must connect while the SITL is up: it runs free once the
            # dead one stops answering (the compiled physics: 300 s in ~7 s here)
            *("--episode-timeout-s", "300", "--lockstep-timeout-s", "0.2"),
        ),
    )
    procs.wait_text("companion", r"-> flying", 60.0)
    # killed soon: lockstep with the compiled physics flies tens of simulated seconds in a
    # fraction of a wall second, and the vehicle must still be well above the ground when the
    # setpoints stop (but have flown some in GUIDED_NOGPS, or no GUID_TIMEOUT runs)
    time.sleep(0.1)
    comp.send_signal(signal.SIGKILL)
    comp.wait(10)
    # restarted in the air (as systemd restarts it), without the operator's --engage-in-air:
    # it connects and says so, and never takes the vehicle that stays in GUIDED_NOGPS, where
    # a setpoint alone would give it back
    procs.start(
        "restarted",
        companion_command(
            ports.remote, ports.camera, tmp_path / "restarted", "--autopilot", "ardupilot",
            *_RELAXED, "--no-engage-in-air",
        ),
    )  # fmt: skip
    procs.wait_text("restarted", r"waiting for a disarm: the vehicle was armed when", 60.0)
    assert sitl.wait(240) == 0
    flight = read_log(sitl_dir / "sitl_seed0_ep0000.mcap")
    texts = [m["text"] for m in flight.topic("/mavlink/in/STATUSTEXT")]
    assert "visland: armed at start, not taking control" in texts, texts
    assert {m["mode"] for m in flight.topic("/autopilot/command")} == {"GUIDED_NOGPS"}
    last_sp_s = flight.topic("/mavlink/in/SET_ATTITUDE_TARGET")[-1]["time_s"]
    modes = [c for c in flight.topic("/mavlink/in/COMMAND_LONG") if c["command"] == 176]
    assert len(modes) == 1  # the first companion's one request; none after the kill
    (timeout,) = [e for e in flight.topic("/events") if e["kind"] == "guided_timeout"]
    assert 3.0 <= timeout["time_s"] - last_sp_s <= 3.0 + 0.11  # GUID_TIMEOUT, seen at 10 Hz
    assert not any(
        s["text"].startswith("no setpoint") for s in flight.topic("/mavlink/out/STATUSTEXT")
    )  # silent, as ArduCopter
    after = [g for g in flight.topic("/groundtruth/state") if g["time_s"] >= timeout["time_s"] + 5]
    assert len(after) > 50
    held = -after[0]["pos_ned_m"][2]
    assert held > 1.0  # in the air: where it is depends on how far the descent went before the
    # kill (a wall-clock moment in a lockstep that runs as fast as the machine allows)
    for g in after:
        roll, pitch, _ = euler_from_quat(np.asarray(g["quat_wxyz"]))
        assert abs(roll) < math.radians(1.0) and abs(pitch) < math.radians(1.0)
        assert abs(g["vel_ned_m_s"][2]) < 0.1 and abs(-g["pos_ned_m"][2] - held) < 0.5
    result = flight.topic("/episode/result")[-1]
    assert not result["landed"] and result["lockstep_timeouts"] == 1  # then it ran free


def test_card_landing_target_mode_lands_through_land_with_plnd(tmp_path):
    """``--companion-mode landing-target --autopilot ardupilot``: PLND_ENABLED = 1, PLND_TYPE =
    1; the companion requests LAND and streams LANDING_TARGET position_valid = 1 in BODY_FRD."""
    report = _fly_ardupilot(
        tmp_path,
        policy=DEFAULT_VISION_POLICY,
        companion_mode="landing-target",
        episodes=1,
        sitl_args=_PATIENT,
    )
    assert report.summary.success_rate == 1.0, report.per_episode
    assert report.summary.landing_error_m.max <= 0.5
    flight = read_log(report.per_episode[0].log)
    assert {m["mode"] for m in flight.topic("/autopilot/command")} == {"LAND"}
    beats = flight.topic("/mavlink/out/HEARTBEAT")
    assert any(b["custom_mode"] == 9 and b["base_mode"] == 81 | 8 | 128 for b in beats)
    targets = flight.topic("/mavlink/in/LANDING_TARGET")
    assert {(t["frame"], t["position_valid"]) for t in targets} == {(12, 1)}
    result = flight.topic("/episode/result")[-1]
    assert result["landing_target"]["accepted"] > 200
    assert result["landing_target"].get("rejected", 0) == 0
    texts = [e["text"] for e in flight.topic("/events")]
    assert "Precision landing: over the target, descending" in texts
    assert not flight.topic("/mavlink/in/SET_ATTITUDE_TARGET")
