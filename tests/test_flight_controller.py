"""The offboard state machine (:class:`companion.offboard.FlightController`) on a fake link, a
fake log and an injected clock: no sockets, no sleeps, no threads.

Every test drives the controller the way the process loop does (telemetry, then the camera
frame, then a tick) and asserts what it does at exact fake times: the staleness failsafes fire
just after ``max_age_s`` and not just before it, whatever the machine's load. The clock advances
in 1/16 s steps (exact in binary); the autopilot's clock is the companion's minus 90 s, in whole
milliseconds as ATTITUDE and DISTANCE_SENSOR stamp it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import NO_RETURN_CM, FakeMsg, attitude_msg, imu_msg, range_msg

from companion.camera import ReceivedFrame
from companion.contract import Command
from companion.contract.companion_records import CompanionCommandRecord, CompanionObservationRecord
from companion.flight import FlightContext, OffboardConfig
from companion.link import PX4, mavlink
from companion.offboard import FlightController
from companion.runtime import PolicyRuntime
from companion.safety import SafetyConfig, SafetyMonitor
from companion.states import Failsafe, FailsafeReason, FlightResult, FlightState, TouchdownAction
from companion.telemetry import TelemetryStore

T0 = 100.0
DT = 1 / 16
AP_OFFSET_S = 90.0
HOVER = 0.45
POLICY_THRUST = 0.6
POLICY_RATES = [0.2, -0.1, 0.05]


def _px4_mode(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


OFFBOARD, AUTO_LAND, AUTO_LOITER, POSCTL = _px4_mode(6), _px4_mode(4, 6), _px4_mode(4, 3), 3 << 16


class FakeClock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class FakeLink:
    """What the controller uses of :class:`companion.link.MavlinkLink`, recording every send."""

    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock
        self.profile = PX4
        self.target_system: int | None = 1
        self.target_component = 1
        self.connected = True
        self.params: dict[str, float] = {PX4.hover_param: HOVER}
        self.param_requests: list[str] = []
        self.setpoints: list[tuple[float, float, list[float], int]] = []
        self.modes: list[tuple[tuple[int, int], bool]] = []
        self.arms: list[bool] = []
        self.last_send_call_s = 0.0

    def request_param(self, name: str) -> None:
        self.param_requests.append(name)

    def param(self, name: str) -> float | None:
        return self.params.get(name)

    def param_int(self, name: str) -> int | None:
        value = self.params.get(name)
        return None if value is None else int(value)

    def send_setpoint(self, thrust: float, rates: Any, time_boot_ms: int) -> float:
        self.setpoints.append((self.clock(), float(thrust), list(map(float, rates)), time_boot_ms))
        return self.clock()

    def request_mode(self, mode: tuple[int, int], armed: bool) -> None:
        self.modes.append((mode, armed))

    def arm(self, arm: bool) -> None:
        self.arms.append(arm)


class FakeRecorder:
    """A :class:`companion.flight.FlightRecorder` that keeps what it is given."""

    def __init__(self) -> None:
        self.path = Path("fake.mcap")
        self.deferring = False
        self.events: list[tuple[float, str, str, dict[str, Any]]] = []
        self.frames: list[int] = []
        self.commands: list[CompanionCommandRecord] = []
        self.observations: list[CompanionObservationRecord] = []
        self.deferred_writes = 0
        self.scene = None  # no picture in this log (log_scene off)

    def scene_frame(self, frame: Any, rx_s: float) -> None:
        raise AssertionError("scene_frame without a scene")

    def _deferred(self) -> None:
        self.deferred_writes += self.deferring

    def frame(self, frame: ReceivedFrame) -> None:
        self._deferred()
        self.frames.append(frame.frame_id)

    def observation(self, t: float, record: CompanionObservationRecord) -> None:
        self._deferred()
        self.observations.append(record)

    def command(self, t: float, record: CompanionCommandRecord) -> None:
        self._deferred()
        self.commands.append(record)

    def event(self, t: float, kind: str, text: str, **extra: Any) -> None:
        self.events.append((t, kind, text, extra))

    def flight_start(self, t: float, text: str, shadow: bool) -> None:
        self.events.append((t, "flight_start", text, {"shadow": shadow}))

    def flush_pending(self) -> None:
        self.deferring = False

    def kinds(self) -> list[str]:
        return [kind for _, kind, _, _ in self.events]


class ConstantPolicy:
    """Always the same command; ``fail`` makes ``act`` raise (a policy error)."""

    privileged = False

    def __init__(self) -> None:
        self.fail = False
        self.resets = 0

    def initial_state(self) -> int:
        self.resets += 1
        return 0

    def act(self, observation, groundtruth, state):
        if self.fail:
            raise RuntimeError("boom")
        return Command(thrust_norm=POLICY_THRUST, rate_frd_rad_s=POLICY_RATES), state + 1


class Rig:
    """One FlightController and everything around it, driven by hand."""

    def __init__(
        self,
        *,
        shadow: bool = False,
        bench: bool = False,
        on_touchdown: str = "disarm",
        camera_clock: str = "autopilot",
        max_age_s: float = 0.3,
    ) -> None:
        self.clock = FakeClock(T0)
        self.link = FakeLink(self.clock)
        self.store = TelemetryStore()
        self.log = FakeRecorder()
        self.policy = ConstantPolicy()
        self.runtime = PolicyRuntime(self.policy, "constant")
        self.pumped: list[float] = []
        self.frame_id = 0
        ctx = FlightContext(
            OffboardConfig(shadow=shadow, bench=bench, on_touchdown=on_touchdown),
            self.link,  # type: ignore[arg-type]
            self.store,
            camera_clock,
            SafetyMonitor(SafetyConfig(max_age_s=max_age_s)),
            self._pump,
            self.clock,
        )
        self.fc = FlightController(ctx, self.runtime, self.log)

    # ------------------------------------------------------------------ the world

    def _pump(self, timeout_s: float) -> None:
        """Nothing arrives: the wait for the frame's telemetry runs out."""
        self.pumped.append(timeout_s)
        self.clock.t += timeout_s

    @property
    def ap_ms(self) -> int:
        return math.floor((self.clock() - AP_OFFSET_S) * 1000)

    def msg(self, name: str, **fields: Any) -> None:
        self.post(FakeMsg(name=name, **fields))

    def post(self, msg: FakeMsg) -> None:
        """``msg`` arrives now: the telemetry store, then the controller."""
        self.store.update(msg, self.clock())
        self.fc.on_message(msg, self.clock())

    def heartbeat(self, mode: int, armed: bool = True) -> None:
        self.msg(
            "HEARTBEAT",
            custom_mode=mode,
            base_mode=(128 if armed else 0) | 1,
            system_status=4,
            autopilot=12,
        )

    def ack(self, result: int) -> None:
        self.msg("COMMAND_ACK", command=mavlink.MAV_CMD_DO_SET_MODE, result=result)

    def telemetry(self, attitude: bool = True, range_m: float = 5.0) -> None:
        """ATTITUDE, HIGHRES_IMU, DISTANCE_SENSOR stamped now (``range_m`` NaN: no return)."""
        ms = self.ap_ms
        valid = math.isfinite(range_m)
        if attitude:
            self.post(attitude_msg(ms))
        self.post(imu_msg(ms * 1000))
        self.post(
            range_msg(ms, round(range_m * 100) if valid else NO_RETURN_CM, 100 if valid else 1)
        )

    def landed(self, on_ground: bool) -> None:
        state = mavlink.MAV_LANDED_STATE_ON_GROUND if on_ground else mavlink.MAV_LANDED_STATE_IN_AIR
        self.msg("EXTENDED_SYS_STATE", vtol_state=0, landed_state=state)

    def frame(self) -> ReceivedFrame:
        self.frame_id += 1
        autopilot = self.fc.camera_clock == "autopilot"  # a SITL frame: the autopilot's stamp
        time_s = self.ap_ms * 1e-3 if autopilot else self.clock()
        frame = ReceivedFrame(self.frame_id, time_s, np.zeros((128, 128), np.uint8), self.clock())
        self.fc.on_frame(frame)
        return frame

    def step(self, *, frame: bool = True, attitude: bool = True, range_m: float = 5.0) -> None:
        """One loop pass DT later: telemetry, the frame, the timers."""
        self.clock.t += DT
        self.telemetry(attitude=attitude, range_m=range_m)
        if frame:
            self.frame()
        self.fc.on_tick()

    def at(self, t: float, *, frame: bool = False) -> None:
        """A loop pass at time ``t`` (fresh telemetry; a frame only when asked)."""
        self.clock.t = t
        self.telemetry()
        if frame:
            self.frame()
        self.fc.on_tick()

    # ------------------------------------------------------------------ getting there

    @property
    def state(self) -> FlightState:
        return self.fc.state

    def fly(self) -> None:
        """WAITING -> PRESTREAM -> ENGAGING -> FLYING with the autopilot saying yes."""
        self.heartbeat(POSCTL)
        self.step()
        assert self.state is FlightState.PRESTREAM
        while self.state is FlightState.PRESTREAM:
            self.step()
        self.ack(0)
        self.heartbeat(OFFBOARD)
        assert self.state is FlightState.FLYING
        self.step()  # the first flight frame: a policy command


# --------------------------------------------------------------------------- states


def test_states_are_their_log_strings_and_a_failsafe_prints_as_before():
    assert json.dumps([FlightResult.LANDED, TouchdownAction.HAND_BACK]) == '["landed", "hand_back"]'
    assert f"{FlightResult.ENGAGE_FAILED}" == "engage_failed"
    fs = Failsafe(FailsafeReason.CAMERA_STALE, "newest frame 309 ms old (> 300)")
    assert str(fs) == f"{fs}" == "camera_stale: newest frame 309 ms old (> 300)"
    assert OffboardConfig(on_touchdown="hand_back").on_touchdown is TouchdownAction.HAND_BACK
    with pytest.raises(ValueError, match="on_touchdown = 'land'; expected disarm or hand_back"):
        OffboardConfig(on_touchdown="land")


# --------------------------------------------------------------------------- engaging


def test_waits_for_its_inputs_prestreams_one_second_then_engages_and_flies():
    rig = Rig()
    rig.fc.on_tick()
    assert rig.state is FlightState.WAITING and rig.log.events[-1][1:3] == (
        "waiting",
        "no HEARTBEAT",
    )
    rig.heartbeat(POSCTL, armed=False)
    rig.step()
    assert rig.state is FlightState.WAITING and rig.link.arms == []  # the pilot arms, not us
    assert rig.log.events[-1][2] == "disarmed (the pilot arms; --arm for SITL demos)"
    rig.heartbeat(POSCTL)
    rig.step(range_m=0.5)
    assert rig.state is FlightState.WAITING  # never take over on the ground
    rig.step()
    assert rig.state is FlightState.PRESTREAM and rig.link.setpoints == []
    t_prestream = rig.clock()
    for _ in range(15):
        rig.step()
    assert rig.state is FlightState.PRESTREAM  # 15/16 s: not yet
    rig.step()
    assert rig.state is FlightState.ENGAGING and rig.clock() - t_prestream == 1.0
    assert rig.link.modes == [(PX4.offboard, True)]
    assert len(rig.link.setpoints) == 16  # one per pass (16 Hz < 20 Hz prestream rate)
    assert all(sp[1] == HOVER and sp[2] == [0.0, 0.0, 0.0] for sp in rig.link.setpoints)
    assert rig.link.param_requests == [PX4.hover_param]

    rig.ack(0)
    sent = len(rig.link.setpoints)
    same_time = rig.frame()  # rendered before the switch: the neutral answer
    assert len(rig.link.setpoints) == sent + 1 and rig.link.setpoints[-1][1] == HOVER
    assert rig.log.commands[-1].kind == "neutral"
    rig.heartbeat(OFFBOARD)
    assert rig.state is FlightState.FLYING and "flight_start" in rig.log.kinds()
    rig.step()
    _, thrust, rates, stamp = rig.link.setpoints[-1]
    assert (thrust, rates) == (POLICY_THRUST, POLICY_RATES)
    assert stamp == rig.ap_ms > round(same_time.time_s * 1000)  # the frame's own time stamp
    cmd = rig.log.commands[-1]
    assert cmd.policy and cmd.kind == "policy" and cmd.sent
    assert rig.fc.outcome.policy_commands == 1 and rig.log.observations[-1].range_m == 5.0
    assert rig.pumped == []  # the telemetry of the frame's time was there: no wait
    assert rig.log.deferring is False and rig.log.deferred_writes >= 3


def test_offboard_refused_three_times_is_engage_failed():
    rig = Rig()
    rig.heartbeat(POSCTL)
    for attempt in range(1, 4):
        while rig.state is not FlightState.ENGAGING:
            rig.step()
        rig.ack(mavlink.MAV_RESULT_DENIED)
        if attempt < 3:
            assert rig.state is FlightState.PRESTREAM  # retry after the pre-stream again
    assert rig.state is FlightState.DONE
    assert rig.fc.outcome.result is FlightResult.ENGAGE_FAILED
    assert rig.fc.outcome.reason == "OFFBOARD refused 3 times"
    assert rig.link.modes == [(PX4.offboard, True)] * 3


def test_no_ack_retries_and_an_ack_never_confirmed_fails_safe():
    rig = Rig()
    rig.heartbeat(POSCTL)
    while rig.state is not FlightState.ENGAGING:
        rig.step()
    t_engage = rig.clock()
    rig.at(t_engage + 3.0 - DT)
    assert rig.state is FlightState.ENGAGING
    rig.at(t_engage + 3.0 + DT)  # no answer for engage_timeout_s
    assert rig.state is FlightState.PRESTREAM
    while rig.state is not FlightState.ENGAGING:
        rig.step()
    rig.ack(0)
    t_ack = rig.clock()
    for _ in range(int(3.0 / DT)):
        rig.step()
    assert rig.state is FlightState.ENGAGING
    rig.at(t_ack + 3.0 + DT)  # OFFBOARD accepted but the HEARTBEAT never shows it
    assert rig.state is FlightState.FAILSAFE
    fs = rig.fc.outcome.failsafe
    assert fs == Failsafe(
        FailsafeReason.OFFBOARD_UNCONFIRMED, "ACK but no OFFBOARD in the HEARTBEAT"
    )
    assert rig.link.modes[-1] == (PX4.land, True)


# --------------------------------------------------------------------------- failsafes


def test_camera_stale_fails_safe_just_after_max_age_not_before():
    rig = Rig()
    rig.fly()
    last_rx = rig.clock()  # the newest frame; telemetry keeps coming
    rig.at(last_rx + 0.299)
    assert rig.state is FlightState.FLYING and rig.fc.outcome.failsafe is None
    sent = len(rig.link.setpoints)
    rig.at(last_rx + 0.301)
    assert rig.state is FlightState.FAILSAFE
    fs = rig.fc.outcome.failsafe
    assert fs is not None and fs.reason is FailsafeReason.CAMERA_STALE
    assert str(fs) == "camera_stale: newest frame 301 ms old (> 300)"
    assert rig.log.events[-1][2] == (
        "flying -> failsafe: camera_stale: newest frame 301 ms old (> 300): "
        "LAND requested, setpoints stopped"
    )
    assert rig.link.modes[-1] == (PX4.land, True)
    rig.at(last_rx + 0.4, frame=True)  # the camera is back: too late, no more setpoints
    assert len(rig.link.setpoints) == sent
    rig.at(last_rx + 0.301 + 1.5 + DT)  # no ACK, no LAND in the HEARTBEAT: asked again
    assert rig.link.modes[-2:] == [(PX4.land, True)] * 2
    rig.heartbeat(AUTO_LAND)
    rig.heartbeat(AUTO_LAND, armed=False)
    out = rig.fc.outcome
    assert rig.state is FlightState.DONE and out.result is FlightResult.FAILSAFE
    assert out.reason == "camera_stale: newest frame 301 ms old (> 300); landed and disarmed"
    summary = out.to_dict()
    assert summary["result"] == "failsafe" and type(summary["result"]) is str
    assert summary["failsafe_reason"] == "camera_stale: newest frame 301 ms old (> 300)"
    assert json.loads(json.dumps(summary)) == summary


def test_telemetry_stale_names_the_stalest_message():
    rig = Rig(camera_clock="companion")  # a local camera: frames are not synced to telemetry
    rig.fly()
    last_att = rig.store.attitude.rx_s
    for _ in range(4):  # frames, IMU and range keep coming; ATTITUDE stopped
        rig.step(attitude=False)
    assert rig.clock() - last_att == 0.25 and rig.state is FlightState.FLYING
    rig.clock.t = last_att + 0.299
    rig.fc.on_tick()
    assert rig.state is FlightState.FLYING
    rig.clock.t = last_att + 0.301
    rig.fc.on_tick()
    fs = rig.fc.outcome.failsafe
    assert rig.state is FlightState.FAILSAFE and fs.reason is FailsafeReason.TELEMETRY_STALE
    assert str(fs) == "telemetry_stale: attitude 301 ms old (> 300)"


def test_no_valid_range_near_the_ground_fails_safe_on_the_next_frame():
    rig = Rig()
    rig.fly()
    last_valid = rig.clock()
    for _ in range(4):  # 0.25 s of invalid ranges at 5 m (< near_ground_m)
        rig.step(range_m=math.nan)
    assert rig.state is FlightState.FLYING
    rig.step(range_m=math.nan)  # 0.3125 s
    fs = rig.fc.outcome.failsafe
    assert rig.state is FlightState.FAILSAFE and fs.reason is FailsafeReason.RANGE_INVALID
    assert str(fs) == "range_invalid: no valid range for 312 ms at 5.0 m"
    assert rig.clock() - last_valid == 0.3125


def test_a_policy_error_fails_safe_with_its_message():
    rig = Rig()
    rig.fly()
    rig.policy.fail = True
    sent = len(rig.link.setpoints)
    rig.step()
    fs = rig.fc.outcome.failsafe
    assert rig.state is FlightState.FAILSAFE
    assert fs == Failsafe(FailsafeReason.POLICY_ERROR, "RuntimeError: boom")
    assert len(rig.link.setpoints) == sent and rig.link.modes[-1] == (PX4.land, True)


def test_the_pilot_taking_over_in_flight_is_handed_back():
    rig = Rig()
    rig.fly()
    rig.heartbeat(POSCTL)
    assert rig.fc.outcome.result is FlightResult.HANDED_BACK
    assert rig.fc.outcome.reason == "mode changed to POSCTL (not by us)"


# --------------------------------------------------------------------------- touchdown


def _touch_down(rig: Rig) -> None:
    """The autopilot's land detector says ON_GROUND twice, 0.25 s apart, during the flight."""
    rig.landed(on_ground=True)
    for _ in range(4):
        rig.step()
    assert rig.state is FlightState.FLYING  # once is not enough
    rig.landed(on_ground=True)
    rig.step()


def test_touchdown_disarms_then_the_flight_has_landed():
    rig = Rig(on_touchdown="disarm")
    rig.landed(on_ground=True)  # before the flight: ignored
    rig.fly()
    _touch_down(rig)
    assert rig.state is FlightState.TOUCHDOWN and rig.link.arms == [False]
    rig.step()  # frames on the ground are answered with zero thrust
    assert rig.link.setpoints[-1][1:3] == (0.0, [0.0, 0.0, 0.0])
    assert rig.log.commands[-1].kind == "touchdown"
    rig.heartbeat(OFFBOARD, armed=False)
    assert rig.fc.outcome.result is FlightResult.LANDED
    assert rig.fc.outcome.reason == "disarmed on the ground"


def test_touchdown_hand_back_requests_hold_and_lands_when_the_autopilot_holds():
    rig = Rig(on_touchdown="hand_back")
    rig.fly()
    _touch_down(rig)
    assert rig.state is FlightState.TOUCHDOWN
    assert rig.link.arms == [] and rig.link.modes[-1] == (PX4.hold, True)
    rig.heartbeat(OFFBOARD)
    assert rig.state is FlightState.TOUCHDOWN
    rig.heartbeat(AUTO_LOITER)
    assert rig.fc.outcome.result is FlightResult.LANDED
    assert rig.fc.outcome.reason == "handed back in AUTO.LOITER"


def test_touchdown_without_a_disarm_ends_after_five_seconds():
    rig = Rig()
    rig.fly()
    _touch_down(rig)
    t_down = rig.clock()
    rig.at(t_down + 5.0)
    assert rig.state is FlightState.TOUCHDOWN
    rig.at(t_down + 5.0 + DT)
    assert rig.fc.outcome.result is FlightResult.LANDED
    assert rig.fc.outcome.reason == "touchdown; no disarm seen within 5 s"


# --------------------------------------------------------------------------- shadow


def test_shadow_flies_the_policy_sends_nothing_and_a_would_be_failsafe_ends_it():
    rig = Rig(shadow=True)
    rig.heartbeat(POSCTL)
    rig.step()
    assert rig.state is FlightState.FLYING  # straight in: nothing to engage
    for _ in range(5):
        rig.step()
    assert rig.link.setpoints == [] and rig.link.modes == [] and rig.link.arms == []
    assert len(rig.log.commands) == 5
    assert all(c.kind == "shadow" and not c.sent for c in rig.log.commands)
    assert rig.fc.outcome.policy_commands == 5
    last_rx = rig.clock()
    rig.at(last_rx + 0.299)
    assert rig.state is FlightState.FLYING
    rig.at(last_rx + 0.301)
    out = rig.fc.outcome
    assert out.result is FlightResult.SHADOW and out.failsafe.reason is FailsafeReason.CAMERA_STALE
    assert out.reason == "failsafe (shadow): camera_stale: newest frame 301 ms old (> 300)"
    assert "failsafe_shadow" in rig.log.kinds() and rig.link.modes == []


def test_shadow_waits_for_arming_and_range_the_bench_logs_disarmed_on_the_ground():
    """Plain shadow logs nothing on the bench (disarmed, radar below engage_min_range_m);
    bench shadow computes and logs from the first fresh frame, and a would-be failsafe is an
    event (once per reason), not the end of it."""
    shadow = Rig(shadow=True)
    shadow.heartbeat(POSCTL, armed=False)
    for _ in range(4):
        shadow.step(range_m=0.1)
    assert shadow.state is FlightState.WAITING and shadow.log.commands == []
    rig = Rig(shadow=True, bench=True)
    rig.heartbeat(POSCTL, armed=False)
    for _ in range(4):
        rig.step(range_m=0.1)
    assert rig.state is FlightState.FLYING  # from the first tick: the frames after it answered
    assert len(rig.log.commands) == 3 and all(not c.sent for c in rig.log.commands)
    last_rx = rig.clock()
    for k in range(3):  # no camera for 0.3 s and more: a would-be failsafe, logged once
        rig.at(last_rx + 0.301 + k * DT)
    assert rig.state is FlightState.FLYING and rig.log.kinds().count("failsafe_shadow") == 1
    for _ in range(10):  # 0.15 m on the ground with a quiet gyro: no touchdown end either
        rig.step(range_m=0.15)
    assert rig.state is FlightState.FLYING and len(rig.log.commands) == 13
    assert rig.link.setpoints == [] and rig.link.modes == [] and rig.link.arms == []
    with pytest.raises(ValueError, match="bench = true needs shadow = true"):
        OffboardConfig(bench=True)


def test_hand_back_on_exit_requests_the_mode_only_when_in_control():
    rig = Rig()
    rig.fly()
    rig.fc.hand_back("hold", "signal SIGTERM")
    assert rig.link.modes[-1] == (PX4.hold, True)
    assert rig.fc.outcome.result is FlightResult.ABORTED
    assert rig.fc.outcome.reason == "signal SIGTERM"
    waiting = Rig()
    waiting.fc.hand_back("land", "exit")
    assert waiting.link.modes == [] and waiting.fc.outcome.result is FlightResult.ABORTED
