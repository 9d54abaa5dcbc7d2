"""The training schedule of paper 4.3 on a CPU, as resumable stages of one run folder.

    collect     expert flights with camera (in process)                 flights/expert/
    bc          stage 1: privileged LSTM, behaviour cloning             checkpoints/bc.pt
    dagger      stage 1: DAgger rounds (learner flies, relabel, aggregate, retrain)
                                                                        checkpoints/dagger.pt
    perception  stage 2: CNN bearing regression on expert frames (90/10) checkpoints/perception.pt
    vision      stage 3: CNN + estimator replace ground truth; LSTM fine-tuned with DAgger rounds
                where the vision policy flies                           checkpoints/vision.pt
    eval        300 episodes (profile) of expert, BC, DAgger, vision on seeds disjoint from
                training, inference timings                             metrics.json

Each finished stage writes ``stages/<stage>.json``; a rerun skips finished stages (and finished
DAgger rounds), so an interrupted pipeline resumes where it stopped. Every DAgger round leaves
its learner flight logs (``flights/<round>/``) and their offline expert labels
(``labels/<round>/``, written by ``expert.relabel`` exactly as ``visland relabel`` does).
Scalars go to TensorBoard (``tb/``) and ``scalars.jsonl``.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from companion.flightlog import jsonable
from companion.policy_net import (
    ControlLSTM,
    LearnedPolicy,
    NetConfig,
    PerceptionCNN,
    load_networks,
    save_checkpoint,
)
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.scenario import load_scenario
from training.dataset import Episode, load_episodes
from training.perception_data import render_pose_frames
from training.replay import ReplayBuffer
from training.rollout import RolloutSpec, git_commit, log_name, run_episodes
from training.train import (
    net_config_for,
    privileged_episode,
    train_controller,
    train_perception,
    vision_episode,
)

__all__ = [
    "PROFILES",
    "ROLLOUT_TRANSPORTS",
    "STAGES",
    "PipelineError",
    "Profile",
    "Run",
    "inference_timing",
    "run_pipeline",
]

STAGES = ("collect", "bc", "dagger", "perception", "vision", "eval")
ROLLOUT_TRANSPORTS = ("mavlink", "inprocess")


class PipelineError(ValueError):
    """A stage cannot run (missing prerequisite, unusable data); names the stage and file."""


@dataclass(frozen=True)
class Profile:
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
    eval_seed: int = 1_000_000
    batch_segments: int = 32
    lr: float = 1e-3
    finetune_lr: float = 5e-4
    buffer_capacity: int = 400
    segment_steps: int = 25
    burn_in_steps: int = 0
    workers: int = 2
    """Parallel in-process workers, or SITL + companion pairs for ``mavlink`` rollouts."""
    rollouts: str = "mavlink"
    """How DAgger learner rollouts fly: ``mavlink`` (default) — the SITL and the companion as
    separate processes over UDP in lockstep, ``workers`` pairs side by side, the SITL's flight
    logs relabelled; ``inprocess`` — the gymnasium env in worker processes (faster, same
    physics). Expert collection, validation and evaluation fly in process either way."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.rollouts not in ROLLOUT_TRANSPORTS:
            raise PipelineError(
                f"profile {self.name!r}: rollouts = {self.rollouts!r}; expected one of "
                f"{', '.join(ROLLOUT_TRANSPORTS)}"
            )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


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
}


class Run:
    """One run folder: stage records, checkpoints, flights, labels, scalars, metrics."""

    def __init__(
        self,
        out: str | Path,
        profile: Profile,
        scenario: str | None = None,
        progress: bool = True,
        say: Callable[[str], None] | None = None,
    ) -> None:
        self.root = Path(out)
        self.profile = profile
        self.scenario_path = scenario
        self.progress = progress
        self.say = say or (lambda msg: print(msg, file=sys.stderr, flush=True))
        self.vehicle = load_vehicle()
        self.sim = load_sim()
        self.scenario = load_scenario(scenario) if scenario else load_scenario()
        planet = self.scenario.planet if getattr(self.scenario, "planet", None) else None
        self.planet = planet or self.sim.planet
        self.commit = git_commit()
        for sub in ("stages", "checkpoints", "flights", "labels", "cache"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self._check_profile()
        self._tb = None
        self._scalars = (self.root / "scalars.jsonl").open("a")

    # ------------------------------------------------------------------ bookkeeping

    def _check_profile(self) -> None:
        path = self.root / "profile.json"
        mine = {"profile": self.profile.to_dict(), "scenario": self.scenario_path}
        if path.exists():
            theirs = json.loads(path.read_text())
            added = sorted(set(mine["profile"]) - set(theirs.get("profile", {})))
            if added and theirs.get("profile", {}).get("name") == self.profile.name:
                # a run started before these profile keys existed: the stages it has done keep
                # their records (and commits); stages run from now on use the new keys
                theirs["profile"] = {**theirs["profile"], **{k: mine["profile"][k] for k in added}}
                theirs.setdefault("upgraded", []).append({"commit": self.commit, "keys": added})
                path.write_text(json.dumps(theirs, indent=2))
            if {k: theirs.get(k) for k in mine} != mine:
                prof = theirs.get("profile") or {}
                keys = sorted(k for k in mine["profile"] if prof.get(k) != mine["profile"][k])
                if theirs.get("scenario") != mine["scenario"]:
                    keys.append("scenario")
                raise PipelineError(
                    f"{path}: this run was started with another profile/scenario "
                    f"({prof.get('name')!r}; differs in {', '.join(keys)}); use a new --out "
                    "folder"
                )
        else:
            path.write_text(json.dumps(mine, indent=2))

    def log(self, name: str, value: float, step: int) -> None:
        if self._tb is None:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(str(self.root / "tb"))
            except ImportError:  # tensorboard is a dependency; never fail a run over it
                self._tb = False
        if self._tb:
            self._tb.add_scalar(name, value, step)
        self._scalars.write(json.dumps({"name": name, "value": value, "step": step}) + "\n")

    def close(self) -> None:
        if self._tb:
            self._tb.close()
        self._scalars.close()

    def done(self, stage: str) -> dict[str, Any] | None:
        path = self.root / "stages" / f"{stage}.json"
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except ValueError:
            return None  # a half-written record: redo the stage

    def finish(self, stage: str, record: dict[str, Any]) -> dict[str, Any]:
        record = {"stage": stage, "git_commit": self.commit, **record}
        path = self.root / "stages" / f"{stage}.json"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(jsonable(record), indent=2))
        tmp.replace(path)
        return record

    def need(self, stage: str) -> dict[str, Any]:
        rec = self.done(stage)
        if rec is None:
            raise PipelineError(
                f"stage {stage!r} of {self.root} has not finished; run it first "
                f"(visland train {stage} --run {self.root})"
            )
        return rec

    def bar(self, total: int, desc: str) -> tqdm:
        return tqdm(total=total, desc=desc, file=sys.stderr, disable=not self.progress)

    def net_config(self, kind: str) -> NetConfig:
        return net_config_for(self.vehicle, self.sim, kind, self.planet)

    def metadata(self, stage: str, data: dict[str, Any]) -> dict[str, Any]:
        return {
            "stage": stage,
            "profile": self.profile.name,
            "run": str(self.root),
            "git_commit": self.commit,
            "scenario": self.scenario_path or "configs/scenario.toml",
            "data": data,
            "created_unix": time.time(),
        }

    # ------------------------------------------------------------------ flights

    def fly(
        self,
        checkpoint: str,
        seed: int,
        count: int,
        folder: str,
        camera: bool,
        transport: str | None = None,
    ) -> list[Path]:
        """Rollouts of episodes ``0..count-1`` of ``seed`` with their flight logs in
        ``flights/<folder>/``; resumable (complete logs are not flown again).

        ``transport`` (default: the profile's ``rollouts``): ``mavlink`` flies the policy
        through ``visland sitl`` + ``visland companion`` processes (``training.fly.fly_many``,
        lockstep, ``workers`` pairs) and returns the SITL's logs — the training record;
        ``inprocess`` flies the gymnasium env in ``workers`` processes."""
        from training.rollout import completed_episode

        transport = transport or self.profile.rollouts
        flights = self.root / "flights" / folder
        flights.mkdir(parents=True, exist_ok=True)
        if transport == "mavlink":
            from training.fly import sitl_log_name

            paths = [flights / sitl_log_name(seed, i) for i in range(count)]
        else:
            paths = [flights / log_name(seed, i) for i in range(count)]
        todo = [i for i, path in enumerate(paths) if not completed_episode(path)]
        if not todo:
            return paths
        with self.bar(len(todo), f"fly {folder} ({transport})") as bar:
            if transport == "mavlink":
                self._fly_mavlink(checkpoint, seed, todo, flights, camera, bar.update)
            else:
                spec = RolloutSpec(
                    policy=checkpoint,
                    seed=seed,
                    scenario=self.scenario_path,
                    render_camera=camera,
                    log_dir=str(flights),
                )
                run_episodes(spec, todo, self.profile.workers, on_done=lambda _: bar.update())
        return paths

    def _fly_mavlink(
        self,
        checkpoint: str,
        seed: int,
        todo: list[int],
        flights: Path,
        camera: bool,
        progress: Callable[[int], Any],
    ) -> None:
        """SITL + companion pairs; a failed pair's episodes are flown once more, then a
        PipelineError names what failed (the logs that finished stay: a rerun resumes)."""
        from training.fly import FlyConfig, FlyError, fly_many, sitl_log_name
        from training.rollout import completed_episode

        cfg = FlyConfig(
            policy=checkpoint,
            seed=seed,
            scenario=self.scenario_path,
            render=camera,
            out=str(flights / "mavlink"),
            sitl_log_dir=str(flights),
            progress=False,
        )
        for attempt in (1, 2):
            try:
                fly_many(cfg, todo, instances=self.profile.workers, on_done=progress)
                return
            except FlyError as exc:
                todo = [i for i in todo if not completed_episode(flights / sitl_log_name(seed, i))]
                if attempt == 2:
                    raise PipelineError(
                        f"{flights}: {len(todo)} SITL + companion rollouts failed twice "
                        f"(rerun to resume): {exc}"
                    ) from None
                self.say(f"fly: {exc}\nflying the {len(todo)} missing episodes again")

    def relabel(self, logs: list[Path], folder: str) -> list[tuple[Path, Path]]:
        """Offline expert labels for learner logs (``expert.relabel``, as `visland relabel`)."""
        from expert.relabel import label_path, relabel

        out = self.root / "labels" / folder
        todo = [p for p in logs if not label_path(p, out).exists()]
        if todo:
            t0 = time.perf_counter()
            reports = relabel(todo, out, workers=self.profile.workers)
            bad = [r for r in reports if r.error]
            for r in bad:
                self.say(f"relabel: {r.error}")
            self.say(f"relabelled {len(todo)} logs in {time.perf_counter() - t0:.0f} s")
        return [(p, label_path(p, out)) for p in logs if label_path(p, out).exists()]

    def episodes(self, pairs: list[tuple[Path, Path | None]], images: bool) -> list[Episode]:
        eps, errors = load_episodes(pairs, with_images=images, cache_dir=self.root / "cache")
        for e in errors:
            self.say(f"skipped: {e}")
        if not eps:
            raise PipelineError(f"{self.root}: no usable episodes ({len(errors)} unreadable)")
        return eps

    def expert_pairs(self) -> list[tuple[Path, Path | None]]:
        rec = self.need("collect")
        return [(Path(p), None) for p in rec["logs"]]

    # ------------------------------------------------------------------ stages

    def stage_collect(self) -> dict[str, Any]:
        p = self.profile
        t0 = time.perf_counter()
        logs = self.fly(
            "expert", p.collect_seed, p.collect_episodes, "expert", True, transport="inprocess"
        )
        return self.finish(
            "collect",
            {
                "logs": [str(x) for x in logs],
                "seed": p.collect_seed,
                "seconds": time.perf_counter() - t0,
            },
        )

    def _privileged_buffer(self, rounds_done: int) -> tuple[ReplayBuffer, list[str]]:
        """The stage-1 buffer: expert flights then each finished DAgger round, FIFO."""
        p = self.profile
        buf = ReplayBuffer(p.buffer_capacity, p.segment_steps, seed=p.seed)
        names = []
        for ep in self.episodes(self.expert_pairs(), images=False):
            buf.add(privileged_episode(ep))
            names.append(ep.name)
        for k in range(rounds_done):
            rec = self.need(f"dagger_r{k}")
            pairs = [(Path(a), Path(b)) for a, b in rec["pairs"]]
            for ep in self.episodes(pairs, images=False):
                buf.add(privileged_episode(ep))
                names.append(ep.name)
        return buf, names

    def _train(
        self,
        control: ControlLSTM,
        buf: ReplayBuffer,
        steps: int,
        lr: float,
        tag: str,
        seed: int,
    ) -> dict[str, Any]:
        p = self.profile
        with self.bar(steps, f"train {tag}") as bar:
            fit = train_controller(
                control,
                buf,
                steps,
                batch_segments=p.batch_segments,
                lr=lr,
                seed=seed,
                burn_in_steps=p.burn_in_steps,
                log=self.log,
                log_prefix=f"controller/{tag}",
                progress=bar.update,
            )
        self.say(f"{tag}: {steps} steps, loss {fit.final_loss:.4f}, {fit.seconds:.0f} s")
        return {
            "steps": steps,
            "final_loss": fit.final_loss,
            "seconds": fit.seconds,
            "buffer_episodes": len(buf),
            "buffer_steps": buf.total_steps,
        }

    def stage_bc(self) -> dict[str, Any]:
        p = self.profile
        torch.manual_seed(p.seed)
        cfg = self.net_config("privileged")
        control = ControlLSTM(cfg)
        buf, names = self._privileged_buffer(0)
        fit = self._train(control, buf, p.bc_steps, p.lr, "bc", p.seed)
        path = save_checkpoint(
            self.root / "checkpoints" / "bc.pt",
            cfg,
            control,
            None,
            self.metadata("bc", {"episodes": names, "fit": fit}),
        )
        return self.finish("bc", {"checkpoint": str(path), **fit})

    def stage_dagger(self) -> dict[str, Any]:
        p = self.profile
        ckpt = Path(self.need("bc")["checkpoint"])
        rounds = []
        for k in range(p.dagger_rounds):
            name = f"dagger_r{k}"
            rec = self.done(name)
            if rec is None:
                logs = self.fly(str(ckpt), p.dagger_seed + k, p.dagger_rollouts, name, camera=False)
                pairs = self.relabel(logs, name)
                cfg, control, _, _ = load_networks(ckpt)
                # expert flights, earlier rounds, then this round (FIFO at capacity)
                buf, names = self._privileged_buffer(k)
                for ep in self.episodes(pairs, images=False):
                    buf.add(privileged_episode(ep))
                    names.append(ep.name)
                fit = self._train(control, buf, p.dagger_steps, p.finetune_lr, name, p.seed + 1 + k)
                out = save_checkpoint(
                    self.root / "checkpoints" / f"{name}.pt",
                    cfg,
                    control,
                    None,
                    self.metadata(name, {"episodes": names, "fit": fit, "from": str(ckpt)}),
                )
                rec = self.finish(
                    name,
                    {
                        "checkpoint": str(out),
                        "rollouts": p.rollouts,
                        "pairs": [[str(a), str(b)] for a, b in pairs],
                        **fit,
                    },
                )
            ckpt = Path(rec["checkpoint"])
            rounds.append(rec)
        # model selection on validation flights (never on the evaluation seeds)
        candidates = [str(self.need("bc")["checkpoint"])] + [r["checkpoint"] for r in rounds]
        return self.finish(
            "dagger", {"rounds": len(rounds), **self.select(candidates, camera=False, out="dagger")}
        )

    def select(self, candidates: list[str], camera: bool, out: str) -> dict[str, Any]:
        """Copy the candidate with the best validation score to ``checkpoints/<out>.pt``."""
        scores = [self.validate(c, camera=camera) for c in candidates]
        best = min(scores, key=lambda r: r["score"])
        final = self.root / "checkpoints" / f"{out}.pt"
        cfg, control, cnn, meta = load_networks(best["checkpoint"])
        save_checkpoint(final, cfg, control, cnn, {**meta, "selected_from": scores})
        return {"checkpoint": str(final), "selected": best["checkpoint"], "validation": scores}

    def evaluate(
        self, policy: str, episodes: int, seed: int, camera: bool, progress: bool
    ) -> dict[str, Any]:
        """``training.evaluate.evaluate`` on this run's scenario and workers."""
        from training.evaluate import EvalConfig, evaluate

        return evaluate(
            EvalConfig(
                policy=policy,
                episodes=episodes,
                seed=seed,
                scenario=self.scenario_path,
                workers=self.profile.workers,
                render_camera=camera,
                progress=progress,
            )
        )

    def validate(self, checkpoint: str, camera: bool) -> dict[str, Any]:
        """Fly the validation episodes; score = mean error + 10 m per failed episode."""
        p = self.profile
        rep = self.evaluate(checkpoint, p.validation_episodes, p.validation_seed, camera, False)
        mean = rep["landing_error_m"]["mean"]
        score = (mean if mean is not None else 100.0) + 10.0 * (1.0 - rep["success_rate"])
        out = {
            "checkpoint": checkpoint,
            "score": score,
            "mean_error_m": mean,
            "success_rate": rep["success_rate"],
            "touchdown_speed_mean_m_s": rep["touchdown_speed_m_s"]["mean"],
        }
        self.say(
            f"validation {Path(checkpoint).name}: score {score:.3f} (mean error "
            f"{mean if mean is not None else float('nan'):.3f} m, success "
            f"{100 * rep['success_rate']:.0f} %)"
        )
        return out

    def stage_perception(self) -> dict[str, Any]:
        p = self.profile
        torch.manual_seed(p.seed)
        cfg = self.net_config("vision")
        cnn = PerceptionCNN(cfg)
        eps = self.episodes(self.expert_pairs(), images=True)
        extra = None
        if p.perception_pose_frames > 0:
            t0 = time.perf_counter()
            extra = render_pose_frames(
                p.perception_pose_frames,
                p.seed + 7,
                self.sim.camera,
                cache_dir=self.root / "cache",
                workers=p.workers,
            )
            self.say(
                f"perception: {p.perception_pose_frames} pose-sampled frames "
                f"({time.perf_counter() - t0:.0f} s)"
            )
        n_train = sum(len(range(0, len(e), p.perception_frame_stride)) for e in eps)
        n_train += p.perception_pose_frames
        steps = p.perception_epochs * max(1, int(n_train * 0.9) // 64)
        with self.bar(steps, "train perception") as bar:
            fit = train_perception(
                cnn,
                eps,
                p.perception_epochs,
                seed=p.seed,
                frame_stride=p.perception_frame_stride,
                log=self.log,
                progress=bar.update,
                extra=extra,
            )
        self.say(
            f"perception: val bearing error median {fit.val_bearing_error_px_median:.2f} px, "
            f"p95 {fit.val_bearing_error_px_p95:.2f} px; position error median "
            f"{fit.val_position_error_m_median:.3f} m ({fit.seconds:.0f} s)"
        )
        # the perception checkpoint carries the privileged DAgger controller if it exists yet
        control = ControlLSTM(cfg)
        path = save_checkpoint(
            self.root / "checkpoints" / "perception.pt",
            cfg,
            control,
            cnn,
            self.metadata("perception", {"episodes": [e.name for e in eps], "fit": fit.to_dict()}),
        )
        return self.finish("perception", {"checkpoint": str(path), **fit.to_dict()})

    def _vision_policy(self) -> tuple[NetConfig, ControlLSTM, PerceptionCNN]:
        _, control, _, _ = load_networks(self.need("dagger")["checkpoint"])
        cfg, _, cnn, _ = load_networks(self.need("perception")["checkpoint"])
        assert cnn is not None
        fresh = ControlLSTM(cfg)
        fresh.load_state_dict(control.state_dict())
        return cfg, fresh, cnn

    def _privileged_controllers(self, cfg: NetConfig) -> list[tuple[str, ControlLSTM]]:
        """The stage-1 checkpoints that landed every validation flight with ground truth
        (all of them if none did), by file stem: the controllers a vision policy can start
        from."""
        scores = self.need("dagger").get("validation") or [
            {"checkpoint": self.need("dagger")["checkpoint"], "success_rate": 1.0}
        ]
        good = [s for s in scores if s.get("success_rate", 0.0) >= 1.0] or scores
        out = []
        for rec in good:
            _, control, _, _ = load_networks(rec["checkpoint"])
            fresh = ControlLSTM(cfg)
            fresh.load_state_dict(control.state_dict())
            out.append((Path(rec["checkpoint"]).stem, fresh))
        return out

    def stage_vision(self) -> dict[str, Any]:
        p = self.profile
        cfg, control, cnn = self._vision_policy()
        policy = LearnedPolicy(cfg, control, cnn)
        buf = ReplayBuffer(p.buffer_capacity, p.segment_steps, seed=p.seed + 50)
        names: list[str] = []
        t0 = time.perf_counter()
        for ep in self.episodes(self.expert_pairs(), images=True):
            buf.add(vision_episode(policy, ep))
            names.append(ep.name)
        self.say(
            f"vision features of {len(names)} expert flights: {time.perf_counter() - t0:.0f} s"
        )
        fits = [
            self._train(control, buf, p.vision_bc_steps, p.finetune_lr, "vision_bc", p.seed + 20)
        ]
        ckpt = save_checkpoint(
            self.root / "checkpoints" / "vision_bc.pt",
            cfg,
            control,
            cnn,
            self.metadata("vision_bc", {"episodes": list(names), "fit": fits[-1]}),
        )
        # Candidates 0..: each privileged controller that landed on validation (BC and every
        # DAgger round), as it is, fed by CNN + estimator. Fine-tuning on the expert's flights
        # alone shrinks the controller's gain on the (noisy) position estimate — the expert
        # stays over the pad, so position noise looks uncorrelated with its commands
        # (regression dilution). And privileged validation cannot tell them apart (millimetres
        # for all), while with a noisy estimate a DAgger round's controller — trained on the
        # learner's off-nominal states — can flare where the BC one hits the ground: vision
        # validation decides.
        priors = []
        for name, prior_control in self._privileged_controllers(cfg):
            priors.append(
                str(
                    save_checkpoint(
                        self.root / "checkpoints" / f"vision_prior_{name}.pt",
                        cfg,
                        prior_control,
                        cnn,
                        self.metadata("vision_prior", {"controller": name}),
                    )
                )
            )
        candidates = [*priors, str(ckpt)]
        for k in range(p.vision_rounds):
            name = f"vision_r{k}"
            logs = self.fly(str(ckpt), p.vision_seed + k, p.vision_rollouts, name, camera=True)
            pairs = self.relabel(logs, name)
            policy = LearnedPolicy(cfg, control, cnn)
            for ep in self.episodes(pairs, images=True):
                buf.add(vision_episode(policy, ep))
                names.append(ep.name)
            fits.append(
                self._train(control, buf, p.vision_steps, p.finetune_lr, name, p.seed + 30 + k)
            )
            ckpt = save_checkpoint(
                self.root / "checkpoints" / f"{name}.pt",
                cfg,
                control,
                cnn,
                self.metadata(name, {"episodes": list(names), "fit": fits[-1]}),
            )
            candidates.append(str(ckpt))
        return self.finish(
            "vision",
            {
                "fits": fits,
                "rollouts": p.rollouts if p.vision_rounds else None,
                **self.select(candidates, camera=True, out="vision"),
            },
        )

    def stage_eval(self) -> dict[str, Any]:
        p = self.profile
        rows = {}
        policies = [
            ("expert", "expert", False),
            ("bc", self.need("bc")["checkpoint"], False),
            ("dagger", self.need("dagger")["checkpoint"], False),
            ("vision", self.need("vision")["checkpoint"], True),
        ]
        for row, policy, camera in policies:
            report = self.evaluate(policy, p.eval_episodes, p.eval_seed, camera, self.progress)
            rows[row] = report
            self.say(
                f"eval {row}: mean error {report['landing_error_m']['mean']:.3f} m, "
                f"max {report['landing_error_m']['max']:.3f} m, success "
                f"{100 * report['success_rate']:.1f} %"
            )
        timing = inference_timing(self.need("vision")["checkpoint"], self)
        metrics = {
            "profile": p.to_dict(),
            "git_commit": self.commit,
            "eval_seed": p.eval_seed,
            "episodes": p.eval_episodes,
            "rows": rows,
            "timing": timing,
            "stages": {s: self.done(s) for s in STAGES if s != "eval"},
        }
        path = self.root / "metrics.json"
        path.write_text(json.dumps(jsonable(metrics), indent=2))
        return self.finish("eval", {"metrics": str(path)})


def inference_timing(vision_checkpoint: str, run: Run, steps: int = 300) -> dict[str, Any]:
    """Per-step compute of the MPC expert vs the shipped policy, same process, one thread."""
    from expert.bench import bench_mpc
    from training.bench_policy import bench_policy

    torch.set_num_threads(1)
    policy = bench_policy(vision_checkpoint, steps=steps)
    mpc = bench_mpc()
    return {"policy": policy, "mpc": mpc}


def run_pipeline(
    out: str | Path,
    profile: str | Profile = "quick",
    scenario: str | None = None,
    stages: tuple[str, ...] = STAGES,
    progress: bool = True,
    redo: str | None = None,
) -> dict[str, Any]:
    """Run (or resume) the stages in order; returns the stage records.

    ``redo``: run this stage again although it has finished; the records of the stages after it
    (which were built on it) are removed too, so they run again when asked for.
    """
    prof = PROFILES[profile] if isinstance(profile, str) else profile
    run = Run(out, prof, scenario, progress)
    if redo is not None:
        if redo not in STAGES:
            run.close()
            raise PipelineError(f"unknown stage {redo!r}; stages are {', '.join(STAGES)}")
        for later in STAGES[STAGES.index(redo) :]:
            record = run.root / "stages" / f"{later}.json"
            if record.exists():
                record.unlink()
                run.say(f"stage {later}: record removed, it will run again")
    records = {}
    t0 = time.perf_counter()
    try:
        for stage in stages:
            if stage not in STAGES:
                raise PipelineError(f"unknown stage {stage!r}; stages are {', '.join(STAGES)}")
            rec = run.done(stage)
            if rec is not None:
                run.say(f"stage {stage}: already done")
            else:
                s0 = time.perf_counter()
                run.say(f"stage {stage}: running")
                rec = getattr(run, f"stage_{stage}")()
                run.say(f"stage {stage}: done in {time.perf_counter() - s0:.0f} s")
            records[stage] = rec
    finally:
        run.close()
    timing_path = Path(out) / "pipeline_time.json"
    prev = json.loads(timing_path.read_text()) if timing_path.exists() else {"sessions": []}
    prev["sessions"].append({"stages": list(stages), "seconds": time.perf_counter() - t0})
    timing_path.write_text(json.dumps(prev, indent=2))
    return records
