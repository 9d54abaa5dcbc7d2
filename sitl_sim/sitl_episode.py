"""Episodes and their flight logs: an episode starts in HOLD (armed, frozen), its flight starts
at the take-over, it ends at touchdown + disarm, at the flight timeout or at the HOLD timeout,
and its result closes its MCAP flight log; everything the SITL writes to that log goes through
here.

:class:`EpisodeLifecycle` is a mixin of :class:`~sitl_sim.mavlink_sitl.MavlinkSitl`: it reads
and changes the SITL's ``config``, ``sim``, ``autopilot``, ``clock``, ``results`` and its
episode state (``_episode``, ``_flying``, ``_done``, ``_land_cmd``, ``_wait``), reads the
streamed readings (``_streamed``) and link counters, and announces through its ``_statustext``
and ``_send_heartbeat``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.contract import Command, GroundTruth
from companion.contract.topics import (
    SCHEMA_AUTOPILOT_COMMAND,
    SCHEMA_COMMAND,
    SCHEMA_EPISODE_RESULT,
    SCHEMA_EPISODE_SCENARIO,
    SCHEMA_EVENT,
    SCHEMA_GROUNDTRUTH,
    SCHEMA_LINK_STATS,
    SCHEMA_OBSERVATION,
    SCHEMA_RX_ERROR,
    TOPIC_AUTOPILOT_COMMAND,
    TOPIC_COMMAND,
    TOPIC_EVENTS,
    TOPIC_GROUNDTRUTH,
    TOPIC_LINK_STATS,
    TOPIC_MAVLINK_IN,
    TOPIC_MAVLINK_OUT,
    TOPIC_OBSERVATION,
    TOPIC_RESULT,
    TOPIC_RX_ERRORS,
    TOPIC_SCENARIO,
    mavlink_schema,
)
from companion.flightlog import FlightLogWriter
from sitl_sim.ardupilot import new_autopilot
from sitl_sim.autopilot import Autopilot
from sitl_sim.flight_record import command_msg, groundtruth_msg
from sitl_sim.metrics import EpisodeResult
from sitl_sim.params import param_table, param_value_msg
from sitl_sim.scenario import InitialState
from sitl_sim.world import EpisodeWorld, episode_world

if TYPE_CHECKING:
    from collections.abc import Callable

    from sitl_sim.autopilot import AutopilotParams, LandController
    from sitl_sim.config import SimConfig, VehicleConfig
    from sitl_sim.link_impairment import LinkImpairment
    from sitl_sim.mavlink_endpoint import Inbound, MavlinkEndpoint, RxError
    from sitl_sim.scenario import InitialStateSampler, Scenario
    from sitl_sim.simulator import CameraFrame, Simulator
    from sitl_sim.sitl_clock import SimClock
    from sitl_sim.sitl_config import SitlConfig

__all__ = [
    "Episode",
    "EpisodeLifecycle",
]

log = logging.getLogger("visland.sitl")


@dataclass
class Episode:
    index: int
    initial: InitialState
    seed_key: tuple[int, int]  # (config seed, episode index): a fresh SeedSequence per reset
    start_tick: int
    writer: FlightLogWriter | None


def _jsonable_msg(msg: Any) -> dict[str, Any]:
    d = msg.to_dict()
    for key, value in d.items():
        if isinstance(value, bytes | bytearray):
            d[key] = value.decode("utf-8", errors="replace")
    if "secret_key" in d:  # SETUP_SIGNING: a secret never goes into a log
        d["secret_key"] = "<redacted>"
    return d


class EpisodeLifecycle:
    """Episode start / flight start / end checks / finish, and the flight-log records."""

    config: SitlConfig
    sim_cfg: SimConfig
    vehicle: VehicleConfig
    sim: Simulator
    autopilot: Autopilot
    params: AutopilotParams
    clock: SimClock
    sampler: InitialStateSampler
    scenario: Scenario
    results: list[EpisodeResult]
    episode_timeout_s: float
    endpoint: MavlinkEndpoint
    gcs_endpoint: MavlinkEndpoint | None
    lockstep_timeouts: int
    link_impairment: LinkImpairment | None
    land_controller: LandController
    _land_controller_factory: Callable[[VehicleConfig, Any], LandController]
    _land_controller_vehicle: VehicleConfig

    # ------------------------------------------------------------------ lifecycle

    def _start_episode(self, index: int) -> None:
        initial = self.sampler.sample(index)
        seed_key = (self.config.seed, index)
        if self.link_impairment is not None:
            self.link_impairment.start_episode(index)  # fates and counters from (seed, index)
        world = self._world(index)
        self.sim.reset(initial, np.random.SeedSequence(seed_key), world=world)
        hover_changed = self._tune_for_episode_vehicle()
        self._reset_samples()
        self.autopilot = new_autopilot(
            self.config.autopilot, self.params, armed=self.config.start_armed
        )
        self._offboard_paced = True
        self._reset_precland()
        self._reset_precland_counters()
        self._flying = False
        self._land_cmd = None
        self._wait = None
        self.clock.restart_phase()
        # what was drawn (only with [vehicle] / [visual]: nominal records are unchanged); the
        # airframe factors are what `visland relabel` applies to the logged vehicle file
        drawn = world.record()
        writer = None
        if self.config.log_dir:
            path = Path(self.config.log_dir) / f"sitl_seed{self.config.seed}_ep{index:04d}.mcap"
            writer = FlightLogWriter(
                path,
                metadata={
                    "config": {
                        "sitl": self.config.to_dict(),
                        "sim": self.sim_cfg.to_dict(),
                        "vehicle": self.vehicle.to_dict(),
                        "params": dataclasses.asdict(self.params),
                    },
                    "episode": {"index": index, "seed": self.config.seed, **drawn},
                },
            )
        self._episode = Episode(index, initial, seed_key, self.clock.tick, writer)
        self._log(
            TOPIC_SCENARIO,
            SCHEMA_EPISODE_SCENARIO,
            {
                "episode": index,
                "seed": self.config.seed,
                "initial_state": initial.to_dict(),
                "scenario": self.scenario.to_dict(),
                **drawn,
            },
        )
        if hover_changed:
            # As PX4 announces a changed parameter: a client holding the old value hears it.
            profile = self.config.autopilot
            table = param_table(self.params, self.endpoint.sysid, profile)
            row = [name for name, _, _ in table].index(self.autopilot.hover_param)
            self._send(param_value_msg(self.endpoint.mav, table, row, profile))
        self._statustext(6, f"Episode {index} ready: HOLD")
        self._send_heartbeat()
        log.info("episode %d: initial state %s", index, initial.to_dict())

    def _tune_for_episode_vehicle(self) -> bool:
        """Tune the autopilot for the airframe this episode flies (:attr:`Simulator.
        episode_vehicle`), as a tuned PX4 is: MPC_THR_HOVER is its hover thrust on this planet
        and AUTO.LAND flies it. Returns whether MPC_THR_HOVER changed."""
        vehicle = self.sim.episode_vehicle
        if vehicle != self._land_controller_vehicle:
            self.land_controller = self._land_controller_factory(vehicle, self.sim_cfg.planet)
            self._land_controller_vehicle = vehicle
        hover = vehicle.hover_thrust_norm(self.sim_cfg.planet)
        if hover == self.params.mpc_thr_hover:
            return False
        self.params = dataclasses.replace(self.params, mpc_thr_hover=hover)
        return True

    def _world(self, index: int) -> EpisodeWorld:
        """Episode ``index``'s drawn world, fresh for each reset (the take-over re-runs it from
        the start, like the sensor streams)."""
        return episode_world(self.scenario, self.config.seed, index)

    def _finish_episode(self, aborted: bool = False) -> None:
        ep = self._episode
        if ep is None:
            return
        self._episode = None
        if self.sim.contact is not None and self._flying:
            result = EpisodeResult.from_contact(self.sim.contact)
        else:
            gt = self.sim.ground_truth()
            result = EpisodeResult.timeout(self.sim.time_s, gt.pos_ned_m, gt.vel_ned_m_s)
        if not aborted:
            self.results.append(result)
        record = {"episode": ep.index, "aborted": aborted, **result.to_dict()}
        record["link_stats"] = self.stats.to_dict()
        if self.gcs_endpoint is not None:
            record["gcs_link_stats"] = self.gcs_endpoint.stats.to_dict()
        record["lockstep_timeouts"] = self.lockstep_timeouts
        record.update(self._precland_record())
        imp = self.link_impairment
        if imp is not None:  # what the impaired link did in this episode, per stream
            record["link_impairment"] = {"config": imp.config.to_dict(), "streams": imp.stats()}
        if ep.writer is not None:
            ep.writer.write(TOPIC_RESULT, SCHEMA_EPISODE_RESULT, self.clock.time_s, record)
            ep.writer.close()
        log.info("episode %d %s: %s", ep.index, "aborted" if aborted else "ended", record)
        if not aborted:
            what = "landed" if result.landed else "timeout"
            self._statustext(6, f"Episode {ep.index} {what}: err {result.landing_error_m:.2f} m")

    def _next_episode(self) -> bool:
        flown = len(self.results)
        if flown >= self.config.episodes:
            self._done = True
        else:
            self._start_episode(self.config.first_episode + flown)
        return False

    def _start_flight(self) -> None:
        """The take-over happened: the flight starts now, from the initial state, re-seeded
        (HOLD's length and the sensor readings taken while frozen cannot change the flight)."""
        ep = self._episode
        assert ep is not None
        paced = self._precland_paced
        self.sim.reset(ep.initial, np.random.SeedSequence(ep.seed_key), world=self._world(ep.index))
        self._reset_samples()
        self._reset_precland()
        self._land_point_ne = None  # AUTO.LAND's point: where it is engaged in this flight
        self._precland_paced = paced  # a client pacing the frozen HOLD paces the flight
        self._flying = True
        self.clock.restart_phase()
        self._event(
            "flight",
            f"flight starts at t = {self.clock.time_s:.3f} s in {self.autopilot.mode_label}",
        )

    def _episode_over(self) -> bool:
        """Touchdown + disarm, the flight timeout, or HOLD without a take-over for too long."""
        ep = self._episode
        assert ep is not None
        if self._flying and self.sim.contact is not None and not self.autopilot.armed:
            return True
        if self._flying and self.sim.time_s >= self.episode_timeout_s - 1e-9:
            return True
        return not self._flying and (self.clock.tick - ep.start_tick) * self.clock.dt_s >= (
            self.config.hold_timeout_s
        )

    # ------------------------------------------------------------------ flight log

    def _log(self, topic: str, schema: str, body: dict[str, Any]) -> None:
        ep = self._episode
        if ep is not None and ep.writer is not None:
            ep.writer.write(topic, schema, self.clock.time_s, body)

    def _event(self, kind: str, text: str) -> None:
        self._log(TOPIC_EVENTS, SCHEMA_EVENT, {"kind": kind, "text": text})

    def _log_rx_error(self, err: RxError, link: str) -> None:
        self._log(
            TOPIC_RX_ERRORS,
            SCHEMA_RX_ERROR,
            {
                "kind": err.kind,
                "reason": err.reason,
                "length": err.length,
                "src": list(err.addr),
                "link": link,
            },
        )

    def _maybe_log_stats(self) -> None:
        now = time.monotonic()
        if now - self._last_stats_log_wall < 1.0:
            return
        self._last_stats_log_wall = now
        total = self._total_stats()
        errors = total.errors_comm + total.rx_unknown_msgid
        if errors != self._last_errors_logged:
            self._last_errors_logged = errors
            stats = {e.name: e.stats.to_dict() for e in self._endpoints}
            log.warning("MAVLink link errors so far: %s", stats)
            self._log(TOPIC_LINK_STATS, SCHEMA_LINK_STATS, stats)

    def _log_inbound(self, inbound: Inbound) -> None:
        msg = inbound.msg
        name = msg.get_type()
        self._log(
            TOPIC_MAVLINK_IN + name,
            mavlink_schema(name),
            {
                **_jsonable_msg(msg),
                "src_system": msg.get_srcSystem(),
                "src_component": msg.get_srcComponent(),
                "signed": inbound.signed,
                "link": inbound.link,
            },
        )

    def _log_outbound(self, msg: Any) -> None:
        if self._episode is not None and self._episode.writer is not None:
            name = msg.get_type()
            self._log(TOPIC_MAVLINK_OUT + name, mavlink_schema(name), _jsonable_msg(msg))

    def _log_commands(self, cmd: Command | None) -> None:
        """At a control period: what the autopilot flies, and in a control step the training
        record's ``/command``."""
        self._log(
            TOPIC_AUTOPILOT_COMMAND,
            SCHEMA_AUTOPILOT_COMMAND,
            {
                "flight_time_s": self.sim.time_s,
                "mode": self.autopilot.mode_label,
                "armed": cmd is not None,
                "thrust_norm": cmd.thrust_norm if cmd is not None else 0.0,
                "rate_frd_rad_s": cmd.rate_frd_rad_s if cmd is not None else [0.0, 0.0, 0.0],
            },
        )
        if cmd is not None and self._control_step():
            # the command flown for the period after the latest frame: in lockstep its
            # answer (the training record's /command, keyed like the in-process log)
            self._log(
                TOPIC_COMMAND,
                SCHEMA_COMMAND,
                command_msg(cmd, self._frame_id - 1, "offboard"),
            )

    def _log_frame(self, frame_id: int, frame: CameraFrame, gt: GroundTruth) -> None:
        """The camera frame just sent, its pose and ground truth, and in a control step the
        training record's ``/observation``. A lost frame (``frame_drop_prob``) is logged as what
        the client still holds — the last delivered image and its exposure time —, as the
        in-process record does, so the training record stays one entry per control step."""
        ep = self._episode
        if ep is None or ep.writer is None:
            return
        ep.writer.write_image(self.clock.time_s, frame.image, frame_id)
        ep.writer.write_pose(self.clock.time_s, gt.pos_ned_m, gt.quat_wxyz)
        ap = self.autopilot
        self._log(
            TOPIC_GROUNDTRUTH,
            SCHEMA_GROUNDTRUTH,
            {
                **groundtruth_msg(gt, frame_id),  # the same record as the in-process path
                "flight_time_s": gt.time_s,
                "flying": self._flying,
                "mode": ap.mode_label,
                "armed": ap.armed,
            },
        )
        obs = self._streamed_observation(frame_id, frame.exposure_time_s)
        if obs is not None and self._control_step():
            self._log(TOPIC_OBSERVATION, SCHEMA_OBSERVATION, obs)

    def _streamed_observation(self, frame_id: int, image_time_s: float) -> dict[str, Any] | None:
        """What a client holds at this frame: the latest attitude, IMU and range readings this
        SITL sent (before MAVLink's float32 / centimetre encoding), with their own times, in the
        in-process log's ``/observation`` record. None until each has been sent since the
        simulator was last reset."""
        parts = self._streamed
        if any(k not in parts for k in ("attitude", "imu", "range_m")):
            return None
        (att_t, att), (imu_t, imu), (rng_t, rng) = (
            parts["attitude"],
            parts["imu"],
            parts["range_m"],
        )
        return {
            "frame_id": frame_id,
            "image_time_s": image_time_s,
            "attitude_rad": att.attitude_rad,
            "rate_frd_rad_s": att.rate_frd_rad_s,
            "attitude_time_s": att_t,
            "range_m": rng if math.isfinite(rng) else None,
            "range_time_s": rng_t,
            "accel_frd_m_s2": imu.accel_frd_m_s2,
            "imu_time_s": imu_t,
        }
