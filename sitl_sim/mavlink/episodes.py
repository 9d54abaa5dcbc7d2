"""Episodes: an episode starts in HOLD (armed, frozen), its flight starts at the take-over, it
ends at touchdown + disarm, at the flight timeout or at the HOLD timeout, and its result closes
its MCAP flight log.

Episode ``i`` starts at ``InitialStateSampler(scenario, seed).sample(i)``; the flight starts
re-seeded, with the episode's world drawn again as ``episode_world(scenario, seed, i)``, so a
flight does not depend on how long HOLD lasted. With a ``[vehicle]`` scenario section each
episode flies its own airframe, and the autopilot is tuned for it as a tuned PX4 is.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.contract.records import ABSENT, EpisodeResultRecord, EpisodeScenarioRecord, EventKind
from companion.contract.topics import TOPIC_SCENARIO
from companion.live.frame import PAPER_PAD_EXTENT_M, pad_extent_m
from sitl_sim.autopilot.ardupilot import new_autopilot
from sitl_sim.metrics import EpisodeResult
from sitl_sim.world import EpisodeWorld, episode_world

if TYPE_CHECKING:
    from collections.abc import Callable

    from sitl_sim.autopilot.px4 import LandController
    from sitl_sim.config import SimConfig, VehicleConfig
    from sitl_sim.mavlink.clock import SimClock
    from sitl_sim.mavlink.config import SitlConfig
    from sitl_sim.mavlink.flight_log import FlightLog
    from sitl_sim.mavlink.handlers import Handlers
    from sitl_sim.mavlink.links import Links
    from sitl_sim.mavlink.precland_loop import PreclandLoop
    from sitl_sim.mavlink.publisher import Publisher
    from sitl_sim.mavlink.state import FlightState
    from sitl_sim.scenario import InitialState, InitialStateSampler, Scenario
    from sitl_sim.simulator import Simulator

__all__ = ["Episode", "EpisodeSetup", "Episodes"]

log = logging.getLogger("visland.sitl")


@dataclass
class Episode:
    index: int
    initial: InitialState
    seed_key: tuple[int, int]  # (config seed, episode index): a fresh SeedSequence per reset
    start_tick: int
    pad_size_m: tuple[float, float] = PAPER_PAD_EXTENT_M
    """The pad its world drew, as the live view draws it (:func:`companion.live.pad_extent_m`)."""


@dataclass
class EpisodeSetup:
    """What the episodes are drawn from and flown with."""

    config: SitlConfig
    scenario: Scenario
    sampler: InitialStateSampler
    vehicle: VehicleConfig
    sim_cfg: SimConfig
    episode_timeout_s: float
    land_controller_factory: Callable[[VehicleConfig, Any], LandController]


@dataclass(eq=False, repr=False)
class Episodes:
    """Starts, ends and scores the episodes; owns the flight log's opening and closing.

    Args:
        setup: the configuration, scenario and initial-state sampler.
        sim: the simulator (reset at each episode and flight start).
        clock: the SITL clock.
        state: the flight state (a fresh autopilot per episode).
        links: the links (their counters go into the result).
        publisher: announcements (STATUSTEXT, HEARTBEAT) and the sensor sample's reset.
        handlers: the parameter protocol (a changed hover thrust is announced).
        precland: the precision land (reset with each episode and flight).
        flight_log: the episode's log.
    """

    setup: EpisodeSetup
    sim: Simulator
    clock: SimClock
    state: FlightState
    links: Links
    publisher: Publisher
    handlers: Handlers
    precland: PreclandLoop
    flight_log: FlightLog
    results: list[EpisodeResult] = field(init=False, default_factory=list)
    """The episodes flown to their end (an aborted one is not a result)."""
    current: Episode | None = field(init=False, default=None)
    done: bool = field(init=False, default=False)
    """Every episode asked for has been flown."""
    _land_controller_vehicle: VehicleConfig = field(init=False)

    def __post_init__(self) -> None:
        self._land_controller_vehicle = self.setup.vehicle

    @property
    def config(self) -> SitlConfig:
        return self.setup.config

    # ------------------------------------------------------------------ lifecycle

    def start(self, index: int) -> None:
        """Episode ``index``: reset to its initial state in HOLD, a fresh autopilot, its log."""
        cfg = self.config
        initial = self.setup.sampler.sample(index)
        seed_key = (cfg.seed, index)
        if self.links.impairment is not None:
            self.links.impairment.start_episode(index)  # fates and counters from (seed, index)
        world = self._world(index)
        self.sim.reset(initial, np.random.SeedSequence(seed_key), world=world)
        hover_changed = self._tune_for_episode_vehicle()
        self.publisher.reset_samples()
        state = self.state
        state.autopilot = new_autopilot(
            cfg.autopilot, state.autopilot.params, armed=cfg.start_armed
        )
        state.offboard_paced = True
        self.precland.start_episode(index)
        state.flying = False
        state.wait = None
        self.clock.restart_phase()
        # what was drawn (only with [vehicle] / [visual]: nominal records are unchanged); the
        # airframe factors are what `visland relabel` applies to the logged vehicle file
        drawn = world.record()
        if cfg.log_dir:
            self.flight_log.open(
                Path(cfg.log_dir) / f"sitl_seed{cfg.seed}_ep{index:04d}.mcap",
                metadata={
                    "config": {
                        "sitl": cfg.to_dict(),
                        "sim": self.setup.sim_cfg.to_dict(),
                        "vehicle": self.setup.vehicle.to_dict(),
                        "params": dataclasses.asdict(state.autopilot.params),
                    },
                    "episode": {"index": index, "seed": cfg.seed, **drawn},
                },
            )
        self.current = Episode(
            index, initial, seed_key, self.clock.tick, pad_extent_m(drawn.get("pad"))
        )
        self.flight_log.write_record(
            TOPIC_SCENARIO,
            EpisodeScenarioRecord(
                episode=index,
                seed=cfg.seed,
                initial_state=initial.to_dict(),
                scenario=self.setup.scenario.to_dict(),
                **drawn,
            ),
        )
        if hover_changed:
            self.handlers.announce_param(state.autopilot.hover_param)
        self.publisher.statustext(6, f"Episode {index} ready: HOLD")
        self.publisher.heartbeat()
        log.info("episode %d: initial state %s", index, initial.to_dict())

    def _tune_for_episode_vehicle(self) -> bool:
        """Tune the autopilot for the airframe this episode flies (:attr:`Simulator.
        episode_vehicle`), as a tuned PX4 is: MPC_THR_HOVER is its hover thrust on this planet
        and AUTO.LAND flies it. Returns whether MPC_THR_HOVER changed."""
        vehicle = self.sim.episode_vehicle
        planet = self.setup.sim_cfg.planet
        state = self.state
        if vehicle != self._land_controller_vehicle:
            state.land_controller = self.setup.land_controller_factory(vehicle, planet)
            self._land_controller_vehicle = vehicle
        hover = vehicle.hover_thrust_norm(planet)
        params = state.autopilot.params
        if hover == params.mpc_thr_hover:
            return False
        state.autopilot.params = dataclasses.replace(params, mpc_thr_hover=hover)
        return True

    def _world(self, index: int) -> EpisodeWorld:
        """Episode ``index``'s drawn world, fresh for each reset (the take-over re-runs it from
        the start, like the sensor streams)."""
        return episode_world(self.setup.scenario, self.config.seed, index)

    def finish(self, aborted: bool = False) -> None:
        """Score the current episode (a result unless ``aborted``) and close its log."""
        ep = self.current
        if ep is None:
            return
        self.current = None
        if self.sim.contact is not None and self.state.flying:
            result = EpisodeResult.from_contact(self.sim.contact)
        else:
            gt = self.sim.ground_truth()
            result = EpisodeResult.timeout(self.sim.time_s, *gt.pad_relative)
            if not self.state.flying:  # the HOLD timeout: nobody took over
                result = dataclasses.replace(result, took_over=False)
        if not aborted:
            self.results.append(result)
        imp = self.links.impairment
        gcs = self.links.gcs
        record = EpisodeResultRecord(
            episode=ep.index,
            aborted=aborted,
            **result.to_dict(),
            link_stats=self.links.offboard.stats.to_dict(),
            gcs_link_stats=ABSENT if gcs is None else gcs.stats.to_dict(),
            lockstep_timeouts=self.state.lockstep_timeouts,
            **self.precland.record(),
            # what the impaired link did in this episode, per stream
            link_impairment=ABSENT
            if imp is None
            else {"config": imp.config.to_dict(), "streams": imp.stats()},
        )
        self.flight_log.close_with_result(record)
        log.info("episode %d %s: %s", ep.index, "aborted" if aborted else "ended", record.to_dict())
        if not aborted:
            what = "landed" if result.landed else "timeout"
            if result.took_over is False:
                what = "not started (HOLD timeout)"
            self.publisher.statustext(
                6, f"Episode {ep.index} {what}: err {result.landing_error_m:.2f} m"
            )

    def start_next(self) -> None:
        """The next episode, or :attr:`done` when every one has been flown."""
        flown = len(self.results)
        if flown >= self.config.episodes:
            self.done = True
        else:
            self.start(self.config.first_episode + flown)

    def start_flight(self) -> None:
        """The take-over happened: the flight starts now, from the initial state, re-seeded
        (HOLD's length and the sensor readings taken while frozen cannot change the flight)."""
        ep = self.current
        assert ep is not None
        self.sim.reset(ep.initial, np.random.SeedSequence(ep.seed_key), world=self._world(ep.index))
        self.publisher.reset_samples()
        self.precland.reset(keep_paced=True)  # a client pacing the frozen HOLD paces the flight
        self.state.flying = True
        self.clock.restart_phase()
        self.flight_log.event(
            EventKind.FLIGHT,
            f"flight starts at t = {self.clock.time_s:.3f} s in {self.state.autopilot.mode_label}",
        )

    def over(self) -> bool:
        """Touchdown + disarm, the flight timeout, or HOLD without a take-over for too long."""
        ep = self.current
        assert ep is not None
        flying = self.state.flying
        if flying and self.sim.contact is not None and not self.state.autopilot.armed:
            return True
        if flying and self.sim.time_s >= self.setup.episode_timeout_s - 1e-9:
            return True
        return not flying and (self.clock.tick - ep.start_tick) * self.clock.dt_s >= (
            self.config.hold_timeout_s
        )
