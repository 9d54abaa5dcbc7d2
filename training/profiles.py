"""Budgets of a pipeline run: :class:`Profile`, the named :data:`PROFILES`, and the
pipeline's error type (no torch here: reports read a run's profile too)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from companion.policy_net.config import ESTIMATOR_FIELDS
from training.exec.transport import Transport
from training.record import Record
from training.seeds import EVAL_SEED

__all__ = [
    "ESTIMATOR_KEYS",
    "LABEL_KEYS",
    "NET_OPTIONS",
    "PERCEPTION_KEYS",
    "PROFILES",
    "ROLLOUT_TRANSPORTS",
    "VISION_KEYS",
    "PipelineError",
    "Profile",
]

ROLLOUT_TRANSPORTS = (Transport.MAVLINK.value, Transport.INPROCESS.value)
"""The values of the profile key ``rollouts`` (:class:`training.exec.transport.Transport`)."""


ADDED = {"added": True}
"""Field metadata of a profile key added after run folders were made: a ``metrics.json`` of
such a run (the ablation a report reads) has no such key, and reads as the default — the
behaviour of the runs made before it (``training.record``)."""

NET_OPTIONS = (
    "hover_input",
    "accel_bias_states",
    "latency_compensation",
    "radar_gate_sigma",
    "alt_noise_fraction",
    "accel_noise_m_s2",
    "accel_bias_walk_m_s2",
    "visibility_threshold",
    "acquire_threshold",
    "unsure_threshold",
    "unsure_sigma_scale",
    "unsure_max_tilt_deg",
    "radar_terrain_slope_deg",
)
"""The profile keys that are :class:`companion.policy_net.NetConfig` fields of the same name
(passed as they are to ``training.train.net_config_for``)."""

LABEL_KEYS = ("name", "eval_suite_baseline")
"""The profile keys that name a run and what its eval stage flies beside it: two runs that
differ only in them trained and flew the same (an ablation's profile differs in them too)."""

VISION_KEYS = (
    "vision_bc_steps",
    "vision_rounds",
    "vision_rollouts",
    "vision_steps",
    "vision_seed",
    "vision_dagger_from_prior",
    "vision_label_gate",
    "vision_truth_inputs",
)
"""The profile keys only the ``vision`` stage reads (how the vision controller learns): a run
``--from`` another may differ in them, as in estimator settings — the stages it takes
(collect through perception) do not read them."""

PERCEPTION_KEYS = (
    "perception_epochs",
    "perception_frame_stride",
    "perception_pose_frames",
    "perception_site_share",
    "perception_away_fraction",
)
"""The profile keys the ``perception`` stage reads first (how the CNN learns): a run ``--from``
another that differs in them takes its stages before perception and trains perception, vision
and eval itself."""

ESTIMATOR_KEYS = tuple(k for k in NET_OPTIONS if k in ESTIMATOR_FIELDS)
"""The profile keys no network weight depends on (the pad estimator's settings): a finished
run may change them, and the stages that fly with the estimator (``vision``, ``eval``) run
again (``training.run_folder.Run``)."""


class PipelineError(ValueError):
    """A stage cannot run (missing prerequisite, unusable data); names the stage and file."""


@dataclass(frozen=True)
class Profile(Record):
    """Budgets of one pipeline run (see PROFILES)."""

    name: str
    collect_episodes: int
    bc_steps: int
    dagger_rounds: int
    dagger_rollouts: int
    dagger_steps: int
    perception_epochs: int
    perception_frame_stride: int
    perception_pose_frames: int
    """Frames rendered at sampled poses (tilted, low, pad out of view) added to the expert
    frames for CNN training (``training.perception_data``)."""
    vision_bc_steps: int
    vision_rounds: int
    vision_rollouts: int
    vision_steps: int
    eval_episodes: int
    validation_episodes: int = 20
    """Episodes (seed ``validation_seed``, disjoint from training and eval) that pick the best
    checkpoint of a stage: BC or a DAgger round, vision BC or a vision round."""
    validation_seed: int = 500
    collect_seed: int = 0
    dagger_seed: int = 100
    vision_seed: int = 200
    eval_seed: int = EVAL_SEED
    batch_segments: int = 32
    lr: float = 1e-3
    finetune_lr: float = 5e-4
    buffer_capacity: int = 400
    segment_steps: int = 25
    burn_in_steps: int = 0
    workers: int = 2
    """Parallel in-process workers, or SITL + companion pairs for ``mavlink`` rollouts."""
    rollouts: str = Transport.MAVLINK.value
    """How DAgger learner rollouts fly: ``mavlink`` (default) — the SITL and the companion as
    separate processes over UDP in lockstep, ``workers`` pairs side by side, the SITL's flight
    logs relabelled; ``inprocess`` — the gymnasium env in worker processes (faster, same
    physics). Expert collection, validation and evaluation fly in process either way."""
    seed: int = 0
    worlds: str | None = None
    """A training-worlds file (``training.worlds``): every stage that flies splits its
    episodes over its scenarios by share. None: the run's one scenario."""
    hover_input: bool = False
    """The controller reads the autopilot's hover thrust (``NetConfig.hover_input``)."""
    accel_bias_states: bool = False
    """The pad estimator estimates acceleration biases (``NetConfig.accel_bias_states``)."""
    latency_compensation: bool = False
    """Camera fixes at the image's exposure time (``NetConfig.latency_compensation``)."""
    radar_gate_sigma: float = 0.0
    """The estimator's radar innovation gate (``NetConfig.radar_gate_sigma``; 0: none)."""
    alt_noise_fraction: float = 0.0
    """The radar noise that grows with range (``NetConfig.alt_noise_fraction``)."""
    accel_noise_m_s2: float = field(default=0.3, metadata=ADDED)
    """The estimator's process noise: how far one IMU sample per control period is trusted
    (``NetConfig.accel_noise_m_s2``)."""
    accel_bias_walk_m_s2: float = field(default=0.02, metadata=ADDED)
    """Random walk of the estimator's acceleration-bias states
    (``NetConfig.accel_bias_walk_m_s2``)."""
    visibility_threshold: float = field(default=0.5, metadata=ADDED)
    """The CNN's pad probability at or above which its bearing is a fix
    (``NetConfig.visibility_threshold``)."""
    acquire_threshold: float | None = field(default=None, metadata=ADDED)
    """... and at or above which a fix may start the estimate (``NetConfig.acquire_threshold``;
    None: ``visibility_threshold``)."""
    unsure_threshold: float | None = field(default=None, metadata=ADDED)
    """... and at or above which, below ``visibility_threshold``, a fix is an unsure one: used
    only when it agrees with the estimate (``NetConfig.unsure_threshold``; None: not used)."""
    unsure_sigma_scale: float = field(default=2.0, metadata=ADDED)
    """Factor on an unsure fix's noise (``NetConfig.unsure_sigma_scale``)."""
    unsure_max_tilt_deg: float | None = field(default=None, metadata=ADDED)
    """No unsure fix from a view tilted beyond this (``NetConfig.unsure_max_tilt_deg``)."""
    radar_terrain_slope_deg: float = field(default=0.0, metadata=ADDED)
    """The steepest ground the radar's beam may meet (``NetConfig.radar_terrain_slope_deg``;
    0: flat, the range is the height above the pad)."""
    vision_dagger_from_prior: bool = False
    """Vision DAgger rounds start from the best privileged controller fed by CNN + estimator
    (by validation) instead of vision BC, and train on the learner's relabelled flights only
    (not the expert's, whose near-perfect vision features teach the controller to ignore the
    position estimate: regression dilution). False: the paper profile's schedule."""
    vision_label_gate: bool = field(default=False, metadata=ADDED)
    """Vision DAgger rounds learn a learner step's label only where the estimate it flew by
    had the pad (:class:`training.train.LabelGate`: position within max(2 m, 10 % of the
    altitude), velocity within 1 m/s of the truth); elsewhere the label is a dash to a pad the
    learner did not know of, and fitting it made the first round of a robust run fly worse than
    the controller it started from (0 % on the nominal world). False: every step learnt."""
    vision_truth_inputs: bool = field(default=False, metadata=ADDED)
    """Vision DAgger rounds add each relabelled learner flight twice: with the inputs the
    learner flew by (CNN + estimator, gated by ``vision_label_gate``) and with the true state
    as inputs (privileged DAgger on the vision learner's states). The second keeps the
    controller's gain on the position it is given (fitting noisy estimates alone shrinks it:
    regression dilution) and teaches it the states a vision learner visits; the first teaches
    it the estimate's lag and noise."""
    eval_suite: str | None = None
    """A benchmark suite (``training.suite``) the eval stage also flies the vision policy on,
    beside the Table 3 rows (which fly the run's scenario, or the paper's for a worlds run)."""
    eval_suite_baseline: str | None = None
    """A checkpoint the eval stage flies on ``eval_suite`` too, for the comparison (the
    paper-world model for the robust profile)."""
    perception_site_share: float | None = field(default=None, metadata=ADDED)
    """The share of the pose-sampled frames rendered in the worlds with a site (a pad carried by
    a rover or a deck, ground that is not flat: ``training.perception_data``), the rest in the
    other worlds, each group split by the worlds' shares; None: every world by its share. A
    carried pad is one blob with its carrier from altitude and has a cab beside it close up:
    the CNN needs more of those frames than the flights' shares give."""
    perception_away_fraction: float = field(default=0.0, metadata=ADDED)
    """The share of the pose-sampled frames with no pad in them, the camera 40–300 m from it
    (``PoseSampling.away_fraction``): bare ground of every world, labelled "no pad"."""
    pad_pose_frames: int = field(default=40000, metadata=ADDED)
    """A run that teaches a pad (``visland pipeline --pad``, ``training.pad_teach``): frames
    rendered at sampled poses with the new pad, the CNN's only data."""
    pad_perception_epochs: int = field(default=2, metadata=ADDED)
    """... the epochs over them (the CNN starts from the ``--from`` model's weights)."""
    pad_perception_lr: float = field(default=1e-3, metadata=ADDED)
    """... and the learning rate (cosine schedule, as for ``perception``)."""
    pad_away_fraction: float | None = field(default=None, metadata=ADDED)
    """... and the share of them over bare ground with no pad (distances scaled with the pad);
    None: ``perception_away_fraction``. A small pad over unseen ground or under a low sun is
    otherwise now and then found in the ground's texture, and the flight lands there."""
    pad_close_fraction: float = field(default=0.0, metadata=ADDED)
    """... and, as a share of them, more frames from 0.3-1.5 m (scaled with the pad) over it,
    labelled with the ``--from`` CNN's own outputs: the pose frames start at 1 m, and a CNN
    fine-tuned on them alone forgets what it answered below, where the controller learned its
    last metres (its pad probability at 0.5-1 m fell from 66 % of frames acquired to 12 %, and
    every taught model touched down at 0.77 m/s where its source did at 0.31)."""
    pad_perception_min_gain: float = field(default=0.8, metadata=ADDED)
    """... and the lowest grey-level gain of its augmentation (uniform up to 1.2): a low sun
    darkens the whole frame (sun 5-12 deg: about 0.4 of the nominal grey levels), which the
    worlds' uniform sun elevations seldom show the CNN."""
    pad_vision_patience: int | None = field(default=1, metadata=ADDED)
    """... and its vision DAgger rounds stop after this many in a row that do not beat the best
    validation score before them (None: every round of ``vision_rounds`` flies). The helipad_1m
    run's three rounds flew 39 of its 57 minutes and none beat the controller it started from."""

    @property
    def teach_away_fraction(self) -> float:
        """The share of a pad teach's pose frames over bare ground (``pad_away_fraction``,
        else ``perception_away_fraction``)."""
        share = self.pad_away_fraction
        return self.perception_away_fraction if share is None else share

    def net_options(self) -> dict[str, bool | float | None]:
        """The :class:`companion.policy_net.NetConfig` fields this profile sets (its
        :data:`NET_OPTIONS`); the rest follow from the vehicle, the world and the camera."""
        return {k: getattr(self, k) for k in NET_OPTIONS}

    @classmethod
    def added_defaults(cls) -> dict[str, object]:
        """The keys marked :data:`ADDED` and their defaults: the behaviour of a run made before
        each existed."""
        return {f.name: f.default for f in fields(cls) if f.metadata.get("added")}

    def __post_init__(self) -> None:
        share = self.perception_site_share
        if share is not None and not 0.0 < share < 1.0:
            raise PipelineError(
                f"profile {self.name!r}: perception_site_share = {share}; expected None or "
                "0 < share < 1"
            )
        if self.pad_vision_patience is not None and self.pad_vision_patience < 1:
            raise PipelineError(
                f"profile {self.name!r}: pad_vision_patience = {self.pad_vision_patience}; "
                "expected None or >= 1 rounds"
            )
        if not 0.0 < self.pad_perception_min_gain <= 1.2:
            raise PipelineError(
                f"profile {self.name!r}: pad_perception_min_gain = "
                f"{self.pad_perception_min_gain}; expected 0 < gain <= 1.2"
            )
        for key in ("perception_away_fraction", "pad_away_fraction", "pad_close_fraction"):
            share = getattr(self, key)
            if share is not None and not 0.0 <= share < 0.5:
                raise PipelineError(
                    f"profile {self.name!r}: {key} = {share}; expected 0 <= share < 0.5"
                )
        if self.rollouts not in ROLLOUT_TRANSPORTS:
            raise PipelineError(
                f"profile {self.name!r}: rollouts = {self.rollouts!r}; expected one of "
                f"{', '.join(ROLLOUT_TRANSPORTS)}"
            )


PROFILES: dict[str, Profile] = {
    # A smoke run of every stage: <= 10 min on 2 cores. Its numbers are not the paper's.
    "quick": Profile(
        name="quick",
        collect_episodes=40,
        bc_steps=1500,
        dagger_rounds=1,
        dagger_rollouts=20,
        dagger_steps=800,
        perception_epochs=15,
        perception_frame_stride=2,
        perception_pose_frames=4000,
        vision_bc_steps=500,
        vision_rounds=1,
        vision_rollouts=16,
        vision_steps=500,
        eval_episodes=20,
        validation_episodes=6,
        pad_pose_frames=2048,
        pad_perception_epochs=1,
    ),
    # Paper 4.3 adapted to 2 CPU cores (<= 60 min): 200 expert flights, BC, 2 privileged DAgger
    # rounds of 60 learner rollouts, CNN on the expert frames, 1 vision DAgger round; 300
    # evaluation episodes per Table 3 row.
    "paper": Profile(
        name="paper",
        collect_episodes=200,
        bc_steps=6000,
        dagger_rounds=2,
        dagger_rollouts=60,
        dagger_steps=3000,
        perception_epochs=5,
        perception_frame_stride=2,
        perception_pose_frames=24000,
        vision_bc_steps=2000,
        vision_rounds=1,
        vision_rollouts=60,
        vision_steps=2500,
        eval_episodes=300,
        validation_episodes=12,
    ),
    # One model for the worlds of issue 16: expert flights and DAgger rollouts across the
    # training worlds of configs/train/robust.toml (Earth and Mars, wind and gusts, +-35 % mass,
    # every ground family and light, camera effects, sensor faults), perception on frames from
    # all of them, the hover-thrust input, estimator bias states and latency compensation.
    # Rollouts in process (the worlds change planet per world; the SITL takes one per process).
    # <= 90 min on 2 cores (docs/results.md has the measured stage times).
    "robust": Profile(
        name="robust",
        collect_episodes=600,
        bc_steps=8000,
        dagger_rounds=2,
        dagger_rollouts=150,
        dagger_steps=4000,
        perception_epochs=6,
        perception_frame_stride=2,
        perception_pose_frames=60000,
        vision_bc_steps=3000,
        vision_rounds=3,
        vision_rollouts=150,
        vision_steps=3000,
        eval_episodes=300,
        validation_episodes=40,
        buffer_capacity=1500,
        rollouts=Transport.INPROCESS.value,
        worlds="configs/train/robust.toml",
        radar_gate_sigma=5.0,
        alt_noise_fraction=0.002,
        accel_noise_m_s2=0.06,
        accel_bias_walk_m_s2=0.002,
        visibility_threshold=0.9,
        acquire_threshold=0.75,
        unsure_threshold=0.5,
        unsure_sigma_scale=3.0,
        unsure_max_tilt_deg=15.0,
        radar_terrain_slope_deg=12.0,
        vision_dagger_from_prior=True,
        vision_label_gate=True,
        vision_truth_inputs=True,
        eval_suite="configs/suites/standard.toml",
        eval_suite_baseline="models/visland_vision_paper.pt",
        hover_input=True,
        accel_bias_states=True,
        latency_compensation=True,
        pad_pose_frames=120000,
        pad_perception_epochs=4,
        pad_perception_min_gain=0.3,
        pad_away_fraction=0.05,
    ),
}

# Ablation of the hover-thrust input: the robust profile with the controller blind to the
# autopilot's hover thrust (its thrust centred on the config's, as the paper-world model's is).
PROFILES["robust_no_hover"] = replace(
    PROFILES["robust"], name="robust_no_hover", hover_input=False, eval_suite_baseline=None
)

# Ablation of the estimator settings chosen on validation after the first robust model: the
# robust networks (`visland pipeline --profile robust_first_estimator --from runs/robust`) with
# that model's estimator — process noise 0.3, bias walk 0.02, a fix at p >= 0.5, no unsure fixes.
PROFILES["robust_first_estimator"] = replace(
    PROFILES["robust"],
    name="robust_first_estimator",
    eval_suite_baseline=None,
    **Profile.added_defaults(),
)

# DAgger that improves with every round (issue 34): the robust profile with four privileged
# rounds, to show the validation curve (`visland pipeline --profile robust_dagger4 --stages
# collect,bc,dagger --out runs/robust_dagger4`; the dagger record holds each round's score).
PROFILES["robust_dagger4"] = replace(
    PROFILES["robust"], name="robust_dagger4", dagger_rounds=4, eval_suite_baseline=None
)

# One policy for every site (issue 34): the robust profile through the sites as well
# (configs/train/robust_sites.toml: a rover, a ship's deck, ground that is not flat on Earth and
# Mars, besides the robust worlds), four privileged DAgger rounds, the shipped model as the
# suite's baseline. The controller's inputs are relative to the pad (what the estimator
# estimates): `visland pipeline --profile robust_sites --out runs/robust_sites`.
PROFILES["robust_sites"] = replace(
    PROFILES["robust"],
    name="robust_sites",
    worlds="configs/train/robust_sites.toml",
    dagger_rounds=4,
    vision_rounds=4,
    eval_suite_baseline="models/visland_vision.pt",
)

# The sites profile with the CNN trained on more site frames (issue 34): 55 % of the pose frames
# in the four site worlds (35 % by their shares). `visland pipeline --profile robust_sites_cnn
# --from runs/robust_sites --out runs/robust_sites_cnn` takes collect through dagger and trains
# perception, vision and eval; `visland pad error` measures the CNN per site and altitude.
PROFILES["robust_sites_cnn"] = replace(
    PROFILES["robust_sites"], name="robust_sites_cnn", perception_site_share=0.55
)

# The sites CNN that knows bare ground (issue 34): robust_sites_cnn's CNN acquires a pad
# (p >= 0.75) in 53 % of level frames of bare nominal ground at 8-20 m (`visland pad error`'s
# false acq; the shipped model's: 2 %) and lands with no pad in view; here 10 % of the pose frames
# show ground with no pad in it. One vision round: robust_sites_cnn's rounds 1-3 did not beat
# round 0 on validation (82.5 %; its vision record). `visland pipeline --profile
# robust_sites_clear --from runs/robust_sites --out runs/robust_sites_clear`.
PROFILES["robust_sites_clear"] = replace(
    PROFILES["robust_sites_cnn"],
    name="robust_sites_clear",
    perception_away_fraction=0.1,
    vision_rounds=1,
)

# ... with 3 % of the pose frames bare ground: robust_sites_clear's 10 % took the false fixes on
# bare nominal ground to 0 (no pad in view: 50 aborts, 0 off the pad) but cost the hard light
# (low sun over every ground 86 %, Mars + wind + faults + low sun 66 %; its CNN sees the pad at
# 40-100 m in 55 % of level frames where robust_sites_cnn's saw 82 %). `visland pipeline
# --profile robust_sites_clear3 --from runs/robust_sites --out runs/robust_sites_clear3`.
PROFILES["robust_sites_clear3"] = replace(
    PROFILES["robust_sites_clear"], name="robust_sites_clear3", perception_away_fraction=0.03
)

# Teach the shipped model the sites (issue 32): a pad run (`visland pipeline --profile
# robust_sites_teach --pad configs/pads/paper.toml --from models/visland_vision.pt --out
# runs/sites_teach`) keeps the shipped controller and fine-tunes its CNN — which knows bare
# ground (2 % false fixes where robust_sites_cnn's, trained from scratch on the sites, had 53 %)
# — on frames of the robust_sites worlds, 55 % of them with a site and 5 % over bare ground, at
# the robust teach's low-sun gains; no vision round (the controller is the shipped one).
PROFILES["robust_sites_teach"] = replace(
    PROFILES["robust"],
    name="robust_sites_teach",
    worlds="configs/train/robust_sites.toml",
    perception_site_share=0.55,
    perception_away_fraction=0.05,
    vision_rounds=0,
    eval_suite_baseline=None,
)

# Teach the shipped model painted ground (issue 34): the field suite's parking lot took the shipped
# CNN's fix on its bays (`visland pad error`: false seen 69 % at 8-20 m; 0 % landed, 40 of 40
# validation flights off the pad). A pad run of the paper pad (`visland pipeline --profile
# robust_field_teach --pad configs/pads/paper.toml --from models/visland_vision.pt --out
# runs/field_teach`) fine-tunes the CNN on the robust worlds, whose Earth world paints markings on
# 60 % of its grounds ([visual] markings), 5 % of the pose frames over bare ground; the shipped
# controller flies it as it is. Chosen on the validation seed (the field suite, 40 flights per
# picture): the robust profile's vision rounds after such a teach cost precision (grass 0.14 ->
# 0.29 m) and 15 % of the frames over bare ground landed fewer on the parking lot (45 % where 5 %
# gave 65 %). 10 % more frames below 1.5 m carry the shipped CNN's own answers there
# (pad_close_fraction): without them the taught CNN touched down at 0.77 m/s (every CNN-only teach
# does: sites 0.76, helipad 0.53). Measured (validation seed, 40 flights per picture; not shipped):
# touchdown 0.63 m/s, close-range acquisition back to 53-62 % of frames (shipped 60-66 %), but the
# parking lot 22 % with 20 off the pad; without the close frames 65 % with 8 off. Open.
PROFILES["robust_field_teach"] = replace(
    PROFILES["robust"],
    name="robust_field_teach",
    pad_close_fraction=0.1,
    vision_rounds=0,
    eval_suite_baseline=None,
)

# The sites teach with close frames (issue 34): robust_sites_teach's CNN touches down at 0.76 m/s
# (it forgets what the shipped CNN answered below 1.5 m, where the controller learned its last
# metres); 10 % more frames from 0.3-1.5 m labelled with the shipped CNN's own outputs, as
# robust_field_teach does. `visland pipeline --profile robust_sites_close --pad
# configs/pads/paper.toml --from models/visland_vision.pt --out runs/sites_close`. Measured on the
# validation seed against robust_sites_teach (24 flights per condition, 40 per ground picture;
# not shipped): touchdown 0.5-0.6 m/s where the teach's is 0.75, but fewer landings — sites
# 517 vs 551 points of success over seven conditions, 23 vs 18 off the pad; Mars + wind +
# faults + low sun 71 vs 96 %; the parking lot 17.5 % (20 off the pad) vs 45 % (10).
PROFILES["robust_sites_close"] = replace(
    PROFILES["robust_sites_teach"], name="robust_sites_close", pad_close_fraction=0.1
)
