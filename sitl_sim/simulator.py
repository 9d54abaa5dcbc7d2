"""The vehicle simulator: physics + autopilot rate loop + sensors + camera, advanced in sim time.

One :class:`Simulator` is one vehicle in one world. It knows nothing of episodes' start or end
rules beyond reporting the first ground contact; the gymnasium env and the MAVLink SITL build on
it. Randomness comes from the seed given to :meth:`Simulator.reset` only (and, with wind,
visual effects or sensor faults, from the episode's :class:`~sitl_sim.physics.wind.WindModel`,
:class:`~sitl_sim.render.visual.VisualSample` and
:class:`~sitl_sim.physics.sensor_faults.SensorFaults`, which
carry their own generators). The vehicle given to the constructor is the vehicle file; each
episode flies :attr:`Simulator.episode_vehicle`, that file scaled by the episode's airframe
factors (a scenario's ``[vehicle]``), if any.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from companion.contract import Command, GroundTruth, Observation
from sitl_sim.config import SimConfig, VehicleConfig
from sitl_sim.errors import SimStateError
from sitl_sim.physics import kernel
from sitl_sim.physics.dynamics import (
    LAYOUT,
    ContactEvent,
    Physics,
    derivative,
    make_state,
    touchdown,
)
from sitl_sim.physics.rate_controller import RateController
from sitl_sim.physics.sensor_faults import SensorFaults
from sitl_sim.physics.sensors import AttitudeSensor, Imu, RadarAltimeter
from sitl_sim.physics.wind import WindModel
from sitl_sim.render.ground import GroundMap, PadGeometry, nominal_ground
from sitl_sim.render.scene import Camera, Renderer, make_renderer
from sitl_sim.render.visual import CameraEffects, VisualSample
from sitl_sim.scenario import InitialState
from sitl_sim.site.contact import SiteContact, quat_from_rotation
from sitl_sim.site.site import Site
from sitl_sim.world import EpisodeWorld

_STILL_AIR = (0.0, 0.0, 0.0)

__all__ = ["CameraFrame", "Simulator"]


@dataclass(frozen=True)
class CameraFrame:
    """The camera's output at one frame time (:meth:`Simulator.capture_frame`).

    Attributes:
        image: (H, W) uint8 mono8.
        exposure_time_s: flight time the image shows (``t - latency``; before 0 for the first
            frames of a flight with latency: the vehicle held its initial state then).
        exposure_step: that time in physics steps (``exposure_time_s = exposure_step * dt``).
        delivered: False when this frame was lost (``frame_drop_prob``): ``image`` and the
            exposure are then the last delivered frame's, what a receiver still holds.
    """

    image: np.ndarray
    exposure_time_s: float
    exposure_step: int
    delivered: bool = True


class Simulator:
    """Physics at ``physics_rate_hz``, camera and control at ``control_rate_hz``.

    Args:
        vehicle: the vehicle and rate-loop configuration (the vehicle file; an episode's world
            may scale it, see :meth:`reset`).
        sim: rates, planet and sensor models.
        scene: a renderer to draw from (:class:`sitl_sim.render.scene.Scene` or
            :class:`sitl_sim.render.render_fast.FastRenderer`; made from ``sim.camera.renderer``
            when
            ``render`` is True; pass one to share it between simulators in one process — each
            reset shows that episode's ground and pad on it).
        render: whether observations carry a rendered camera image (False gives a black frame,
            for physics-only use such as the expert's fast paths and benchmarks).
    """

    def __init__(
        self,
        vehicle: VehicleConfig,
        sim: SimConfig,
        *,
        scene: Renderer | None = None,
        render: bool = True,
    ) -> None:
        self.vehicle = vehicle
        self.sim = sim
        self.phys = Physics(vehicle, sim.planet)
        self.rate_controller = RateController(vehicle.rate_controller, self.phys)
        self.episode_vehicle = vehicle
        """The vehicle this episode flies (``vehicle`` scaled by the world's airframe factors;
        ``vehicle`` itself when the scenario has no ``[vehicle]``)."""
        self._render = render
        self._owns_scene = scene is None and render
        self.scene = (
            scene if scene is not None else (make_renderer(sim.camera.renderer) if render else None)
        )
        self._visual: tuple[VisualSample | None, GroundMap] | None = None  # (sample, its ground)
        self._x: list[float] | None = None
        self._t = 0.0
        self._step_count = 0
        self._rotor_cmd = [0.0] * 4
        self.contact: ContactEvent | None = None
        """The first ground contact since reset, if any."""
        self.wind: WindModel | None = None
        """This episode's wind (None: still air)."""
        self.sensor_faults: SensorFaults | None = None
        """This episode's sensor faults (None: the sensors of the sim config)."""
        self.site: Site | None = None
        """This episode's landing site (None: flat ground, the pad still at the origin)."""
        self._site_contact: SiteContact | None = None
        self._latency_steps = 0
        # (step, position, attitude, body rates) of the last `latency` physics steps
        self._poses: (
            deque[tuple[int, tuple[float, ...], tuple[float, ...], tuple[float, ...]]] | None
        ) = None
        self._last_frame: CameraFrame | None = None

    # ------------------------------------------------------------------ lifecycle

    @property
    def hover_thrust_norm(self) -> float:
        """The episode vehicle's hover thrust on this planet: what the autopilot reports as
        ``MPC_THR_HOVER`` and the Observation carries."""
        return self.episode_vehicle.hover_thrust_norm(self.sim.planet)

    def reset(
        self,
        initial: InitialState,
        seed: int | np.random.SeedSequence,
        world: EpisodeWorld | None = None,
    ) -> None:
        """Place the vehicle at ``initial`` (rotors at hover thrust), reseed every sensor.

        ``world``: the episode's drawn world (:func:`sitl_sim.world.episode_world`), or None for
        the nominal world of the config files. Its wind, a fresh :class:`WindModel`, is started
        here at the initial position, then advanced once per physics step. Its airframe factors
        make :attr:`episode_vehicle`; the physics and the rate loop (tuned for the airframe it
        flies, as a tuned autopilot is) are rebuilt for it when it differs from the last
        episode's, so nominal episodes keep the objects built once. Its visual sample sets the
        ground, pad, light and camera effects. Its sensor faults set the IMU's turn-on biases,
        the radar's faults and the camera's latency (rounded to whole physics steps) and frame
        drops. The sensors' streams do not depend on the world, so a flight without any section
        is the flight it always was.
        """
        world = world or EpisodeWorld()
        wind = world.wind
        faults = world.sensors
        vehicle = world.vehicle(self.vehicle)
        if vehicle != self.episode_vehicle:
            self.phys = Physics(vehicle, self.sim.planet)
            self.rate_controller = RateController(vehicle.rate_controller, self.phys)
            self.episode_vehicle = vehicle
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        imu_ss, att_ss, radar_ss, cam_ss = ss.spawn(4)
        self.imu = Imu(
            self.sim.imu,
            np.random.default_rng(imu_ss),
            accel_bias_frd_m_s2=faults.accel_bias_frd_m_s2 if faults is not None else None,
            gyro_bias_frd_rad_s=faults.gyro_bias_frd_rad_s if faults is not None else None,
        )
        self.attitude_sensor = AttitudeSensor(self.sim.attitude, np.random.default_rng(att_ss))
        site = world.site
        self.site = site
        self._site_contact = SiteContact(site) if site is not None else None
        self.radar = RadarAltimeter(
            self.sim.radar,
            np.random.default_rng(radar_ss),
            faults,
            surface=site.range_along if site is not None else None,
        )
        self.camera = self._camera(world.visual, np.random.default_rng(cam_ss), world.site)
        hover = self.phys.hover_rotor_thrust_n
        self._x = make_state(
            pos_ned_m=initial.pos_ned_m,
            vel_ned_m_s=initial.vel_ned_m_s,
            quat_wxyz=initial.quat_wxyz,
            rate_frd_rad_s=initial.rate_frd_rad_s,
            rotor_thrust_n=(hover,) * 4,
        ).tolist()  # Python floats: several times faster than numpy scalars in the integrator
        self._rotor_cmd = [hover] * 4
        self._t = 0.0
        self._step_count = 0
        self.rate_controller.reset()
        self.contact = None
        self.wind = wind
        if wind is not None:
            wind.start(initial.pos_ned_m)
        self.sensor_faults = faults
        self._latency_steps = (
            round(faults.camera_latency_s * self.sim.physics_rate_hz) if faults is not None else 0
        )
        self._last_frame = None
        self._poses = None
        if self._latency_steps > 0:
            # the poses of the last `latency` steps (oldest first): the camera shows _poses[0]
            self._poses = deque(maxlen=self._latency_steps + 1)
            self._record_pose()

    def _camera(
        self, visual: VisualSample | None, rng: np.random.Generator, site: Site | None = None
    ) -> Camera | None:
        """The episode's camera: its ground and pad shown on the renderer, its light and
        effects (the nominal ground, full light and none without ``[visual]``)."""
        if self.scene is None:
            return None
        if self._visual is None or self._visual[0] != visual:
            ground = visual.ground() if visual is not None else nominal_ground()
            self._visual = (visual, ground)
        ground = self._visual[1]
        if visual is None:
            self.scene.configure(ground, PadGeometry(), site)
            return Camera(self.scene, self.sim.camera, rng)
        self.scene.configure(ground, visual.pad(), site, visual.sun)
        effects = CameraEffects(visual, self.sim.camera, visual.light)
        return Camera(self.scene, self.sim.camera, rng, light=visual.light, effects=effects)

    def close(self) -> None:
        if self._owns_scene and self.scene is not None:
            self.scene.close()
            self.scene = None

    # ------------------------------------------------------------------ stepping

    @property
    def time_s(self) -> float:
        return self._t

    def _state(self) -> list[float]:
        if self._x is None:
            raise SimStateError("Simulator.reset() must be called before stepping or reading")
        return self._x

    def step_physics(self, command: Command | None) -> ContactEvent | None:
        """One physics step. ``command=None`` means disarmed: rotors commanded to zero."""
        return self._advance(command, 1)

    def _advance(self, command: Command | None, n: int) -> ContactEvent | None:
        """``n`` physics steps holding ``command`` in one kernel call
        (:func:`sitl_sim.physics.kernel.period`); ``n`` > 1 only where nothing outside the
        kernel changes between steps (no wind, no site, no camera latency)."""
        x = self._state()
        dt = self.sim.physics_dt_s
        rates = self.rate_controller
        armed, sp_p, sp_q, sp_r, collective = rates.setpoint(command)
        # the wind is held over this step (zero-order hold); the model moves on to its end
        wind = _STILL_AIR if self.wind is None else self.wind.step(dt, self._t, x[0:3], x[3:6])
        contact = self._site_contact
        x_new, rotors, rates.state, touch = kernel.period(
            self.phys.constants, rates.constants, tuple(x), rates.state, armed,
            sp_p, sp_q, sp_r, collective, dt, n, wind[0], wind[1], wind[2], contact is None,
        )  # fmt: skip
        event = None
        if contact is not None:
            x_new, event = contact.resolve(x, list(x_new), self._t, dt)
        elif touch[0] >= 0:
            j, frac, before, free = touch
            event = touchdown(before, free, frac, (self._step_count + j) * dt, dt)
        self._step_count += n
        self._t = self._step_count * dt  # integer count: no drift in sim time
        self._x = list(x_new)
        self._rotor_cmd = list(rotors)
        if self._poses is not None:
            self._record_pose()
        if event is not None and self.contact is None:
            self.contact = event
        return event

    def _record_pose(self) -> None:
        assert self._poses is not None and self._x is not None
        x = self._x
        self._poses.append(
            (
                self._step_count,
                tuple(x[LAYOUT.pos_ned_m]),
                tuple(x[LAYOUT.quat_wxyz]),
                tuple(x[LAYOUT.rate_frd_rad_s]),
            )
        )

    def step(self, command: Command | None) -> ContactEvent | None:
        """Advance one control period (``substeps`` physics steps) holding ``command``.

        Returns the first contact that happened in this period, if any. Without wind, site or
        camera latency the period is one kernel call; else one call per physics step.
        """
        n = self.sim.substeps
        if self.wind is None and self._site_contact is None and self._poses is None:
            return self._advance(command, n)
        first = None
        for _ in range(n):
            event = self._advance(command, 1)
            if event is not None and first is None:
                first = event
        return first

    # ------------------------------------------------------------------ truth and sensors

    def ground_truth(self) -> GroundTruth:
        x = self._state()
        arr = np.asarray(x)
        if self.wind is None:
            d = derivative(x, self._rotor_cmd, self.phys)
        else:
            # the wind now: what the next physics step holds
            d = derivative(x, self._rotor_cmd, self.phys, self.wind.wind_tuple)
        accel = np.asarray(d[3:6])
        contact = self._site_contact
        pad: dict[str, np.ndarray] = {}
        if contact is None:
            if x[2] >= 0.0 and accel[2] >= 0.0:
                accel = np.zeros(3)  # resting on the ground: the normal force balances the rest
        else:
            if contact.resting:
                accel = contact.surface_accel(self._t)  # carried by the surface it rests on
            pad = self._pad_state()
        return GroundTruth(
            time_s=self._t,
            pos_ned_m=arr[LAYOUT.pos_ned_m].copy(),
            vel_ned_m_s=arr[LAYOUT.vel_ned_m_s].copy(),
            quat_wxyz=arr[LAYOUT.quat_wxyz].copy(),
            rate_frd_rad_s=arr[LAYOUT.rate_frd_rad_s].copy(),
            accel_ned_m_s2=accel,
            rotor_thrust_n=arr[LAYOUT.rotor_thrust_n].copy(),
            wind_ned_m_s=self.wind.wind_ned_m_s if self.wind is not None else None,
            **pad,
        )

    def _pad_state(self) -> dict[str, np.ndarray]:
        """GroundTruth's pad fields now (on a site)."""
        assert self.site is not None
        pose = self.site.pad_pose(self._t)
        return {
            "pad_pos_ned_m": pose.position_ned.copy(),
            "pad_vel_ned_m_s": pose.velocity_ned.copy(),
            "pad_quat_wxyz": np.array(quat_from_rotation(pose.R_pad_to_ned)),
            "pad_accel_ned_m_s2": self.site.pad_accel(self._t),
        }

    def on_ground(self) -> bool:
        """The vehicle is on the ground: within 1 cm of the plane (nominal), or resting on a
        site's surface or within 1 cm of it (the land detector's input)."""
        x = self._state()
        contact = self._site_contact
        if contact is None:
            return x[2] > -0.01
        return contact.resting or contact.height_above(x, self._t) < 0.01

    @property
    def camera_latency_steps(self) -> int:
        """The episode's camera latency in physics steps (0 without ``camera_latency_ms``)."""
        return self._latency_steps

    def capture_frame(self, truth: GroundTruth | None = None) -> CameraFrame:
        """The camera's frame now: the scene at ``now - latency`` (the episode's
        ``camera_latency_ms``), or — when this frame is lost (``frame_drop_prob``) — the last
        delivered frame again, marked ``delivered=False``. Call once per frame: each call
        draws the frame's drop. A lost frame is rendered all the same, so the camera noise of
        the frames after it is that of the same flight without drops.

        Without sensor faults this is the render of the current pose at the current time,
        exactly as before faults existed.
        """
        gt = truth or self.ground_truth()
        if self._poses is None:
            step, time_s = self._step_count, gt.time_s
            pos, quat, rate = gt.pos_ned_m, gt.quat_wxyz, gt.rate_frd_rad_s
        else:
            # the oldest pose kept is `latency` steps ago, or the initial state (held before
            # the flight: the SITL's HOLD) while the flight is younger than the latency
            _, pos_t, quat_t, rate_t = self._poses[0]
            pos, quat, rate = np.array(pos_t), np.array(quat_t), np.array(rate_t)
            step = self._step_count - self._latency_steps
            time_s = step * self.sim.physics_dt_s
        if self.camera is not None:
            image = self.camera.capture(pos, quat, rate, time_s)
        else:
            cam = self.sim.camera
            image = np.zeros((cam.height_px, cam.width_px), dtype=np.uint8)
        frame = CameraFrame(image, time_s, step)
        faults = self.sensor_faults
        if faults is not None and faults.frame_dropped() and self._last_frame is not None:
            return CameraFrame(
                self._last_frame.image,
                self._last_frame.exposure_time_s,
                self._last_frame.exposure_step,
                delivered=False,
            )
        self._last_frame = frame
        return frame

    def observe(self, frame_id: int = 0, truth: GroundTruth | None = None) -> Observation:
        """Read every sensor now and render the camera: the deployable policy's input.

        With the episode's sensor faults, ``image_time_s`` is the image's exposure time (``t -
        latency``), and a lost frame repeats the last delivered image with its old
        ``image_time_s`` (a policy sees the staleness there); ``frame_id`` stays the caller's
        control-step id either way: rollout logs and datasets key every record of a step by
        it, and two steps must not share one. ``range_m`` is NaN on a radar dropout.
        """
        gt = truth or self.ground_truth()
        t = gt.time_s
        imu = self.imu.read(
            t, gt.quat_wxyz, gt.accel_ned_m_s2, gt.rate_frd_rad_s, self.sim.planet.gravity_m_s2
        )
        att = self.attitude_sensor.read(t, gt.quat_wxyz, gt.rate_frd_rad_s)
        rng = self.radar.read(gt.pos_ned_m, gt.quat_wxyz, t)
        frame = self.capture_frame(gt)
        return Observation(
            image=frame.image,
            image_time_s=frame.exposure_time_s,
            attitude_rad=att.attitude_rad,
            rate_frd_rad_s=att.rate_frd_rad_s,
            attitude_time_s=t,
            range_m=rng,
            range_time_s=t,
            accel_frd_m_s2=imu.accel_frd_m_s2,
            imu_time_s=t,
            frame_id=frame_id,
            hover_thrust_norm=self.hover_thrust_norm,
        )
