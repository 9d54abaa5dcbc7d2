"""One run folder's bookkeeping: its profile, stage records, scalars, progress bars and the
metadata checkpoints carry.

    profile.json         the profile and scenario the run was started with (checked on resume)
    stages/<stage>.json  finished stages (typed records, ``training.stage_records``)
    checkpoints/ flights/ labels/ cache/
    tb/ scalars.jsonl    training scalars (TensorBoard and one JSON line each)
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from tqdm import tqdm

from companion.flightlog import jsonable
from sitl_sim.config import load_sim, load_vehicle, planet
from training.exec.backend import Backend, LocalBackend
from training.profiles import (
    ESTIMATOR_KEYS,
    LABEL_KEYS,
    PERCEPTION_KEYS,
    VISION_KEYS,
    PipelineError,
    Profile,
)
from training.provenance import git_commit
from training.record import RecordError
from training.stage_records import STAGES, StageRecord, record_type
from training.worlds import load_worlds, single_world

if TYPE_CHECKING:
    from training.pad_teach import PadTeach

__all__ = ["Run"]

S = TypeVar("S", bound=StageRecord)


class Run:
    """One run folder: stage records, checkpoints, flights, labels, scalars, metrics."""

    def __init__(
        self,
        out: str | Path,
        profile: Profile,
        scenario: str | None = None,
        progress: bool = True,
        say: Callable[[str], None] | None = None,
        backend: Backend | None = None,
        pad: PadTeach | None = None,
    ) -> None:
        self.root = Path(out)
        self.profile = profile
        self.pad = pad
        """The pad this run teaches (``training.pad_teach``; None: a run of the whole
        pipeline)."""
        self.backend = backend if backend is not None else LocalBackend(profile.workers)
        """Where the run's episodes fly: rollouts, relabelling, validation, evaluation (not a
        part of the profile: both backends fly the same episodes)."""
        self.scenario_path = scenario
        self.progress = progress
        self.say = say or (lambda msg: print(msg, file=sys.stderr, flush=True))
        self.vehicle = load_vehicle()
        self.sim = load_sim()
        if profile.worlds is not None and scenario is not None:
            raise PipelineError(
                f"profile {profile.name!r} trains across the worlds of {profile.worlds}; "
                f"it takes no --scenario (got {scenario})"
            )
        self.worlds = load_worlds(profile.worlds) if profile.worlds else single_world(scenario)
        self.scenario = self.worlds.worlds[0].scenario
        # one planet: the net config's gravity and hover are that planet's; a mix of planets
        # flies on the sim config's (the estimator's bias states take up the difference)
        planets = self.worlds.planets
        self.planet = planet(planets[0]) if len(planets) == 1 else self.sim.planet
        self.commit = git_commit()
        for sub in ("stages", "checkpoints", "flights", "labels", "cache"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self._check_profile()
        if pad is not None:  # the profile's worlds with the pad, altitudes to its envelope
            from training.pad_teach import pad_worlds

            self.worlds = pad_worlds(self.worlds, pad, self.root / "worlds")
            self.scenario = self.worlds.worlds[0].scenario
        self._tb = None
        self._scalars = (self.root / "scalars.jsonl").open("a")

    def _check_profile(self) -> None:
        path = self.root / "profile.json"
        mine = {"profile": self.profile.to_dict(), "scenario": self.scenario_path}
        if self.pad is not None:
            mine["pad"] = jsonable(self.pad.record.to_dict())
        if path.exists():
            theirs = json.loads(path.read_text())
            if theirs.get("pad") and self.pad is None:
                raise PipelineError(
                    f"{path}: this run teaches pad {theirs['pad'].get('name')!r}; resume it with "
                    f"visland pipeline --pad {theirs['pad'].get('file')} --out {self.root}"
                )
            added = sorted(set(mine["profile"]) - set(theirs.get("profile", {})))
            if added and theirs.get("profile", {}).get("name") == self.profile.name:
                # a run started before these profile keys existed: the stages it has done keep
                # their records (and commits); stages run from now on use the new keys. A key
                # marked ``added`` enters at its default, the behaviour those stages had, so a
                # new value of an estimator key is then a change like any other (below)
                before = Profile.added_defaults()
                theirs["profile"] = {
                    **theirs["profile"],
                    **{k: before.get(k, mine["profile"][k]) for k in added},
                }
                theirs.setdefault("upgraded", []).append({"commit": self.commit, "keys": added})
                path.write_text(json.dumps(theirs, indent=2))
            self._change_estimator(path, theirs, mine)
            if {k: theirs.get(k) for k in mine} != mine:
                prof = theirs.get("profile") or {}
                keys = sorted(k for k in mine["profile"] if prof.get(k) != mine["profile"][k])
                if theirs.get("scenario") != mine["scenario"]:
                    keys.append("scenario")
                if theirs.get("pad") != mine.get("pad"):
                    keys.append("pad")
                raise PipelineError(
                    f"{path}: this run was started with another profile/scenario "
                    f"({prof.get('name')!r}; differs in {', '.join(keys)}); use a new --out "
                    "folder"
                )
        else:
            path.write_text(json.dumps(mine, indent=2))

    def _change_estimator(self, path: Path, theirs: dict, mine: dict) -> None:
        """A run whose profile differs from this one only in estimator settings
        (:data:`ESTIMATOR_KEYS`) takes the new ones: no network weight depends on them, so the
        trained stages stay, and the stages that fly with the estimator (``vision`` on) lose
        their records and run again. ``profile.json`` lists each change (``estimator_changed``:
        commit, old and new values)."""
        prof = theirs.get("profile") or {}
        if prof.get("name") != self.profile.name or theirs.get("scenario") != mine["scenario"]:
            return
        new = mine["profile"]
        differ = {k for k in new if k in prof and prof[k] != new[k]}
        if not differ or not differ <= set(ESTIMATOR_KEYS):
            return
        theirs["profile"] = {**prof, **{k: new[k] for k in differ}}
        theirs.setdefault("estimator_changed", []).append(
            {"commit": self.commit, "keys": {k: {"from": prof[k], "to": new[k]} for k in differ}}
        )
        for stage in STAGES[STAGES.index("vision") :]:
            record = self.record_path(stage)
            if record.exists():
                record.unlink()
                self.say(f"stage {stage}: record removed (estimator settings changed)")
        path.write_text(json.dumps(theirs, indent=2))

    def _check_new_folder(self) -> None:
        """``--from`` starts a run folder: one with stages is resumed without it."""
        if any(self.record_path(s).exists() for s in STAGES):
            raise PipelineError(
                f"{self.root}: --from needs a new run folder (it has stages); to resume this "
                "run, leave out --from"
            )

    def start_from(self, other: str | Path) -> list[str]:
        """Begin this (empty) run from ``other``'s trained stages, for an estimator, a vision
        or a perception ablation: the two profiles may differ only in estimator settings
        (:data:`ESTIMATOR_KEYS`), in how the vision stage learns (:data:`VISION_KEYS`), in how
        the CNN learns (:data:`PERCEPTION_KEYS`) and in what the eval stage flies beside the
        run, so every network ``other`` trained before the first stage that reads a difference
        (collect through perception; through dagger where perception keys differ) is this
        run's too; their records are copied (they keep pointing at ``other``'s checkpoints and
        flights) and the later stages run here with this profile. ``profile.json`` records it
        (``started_from``: run, commit, stages). Returns the stages taken.

        Raises:
            PipelineError: this run has stage records already, ``other`` is not a run folder,
                or the profiles differ in anything else (named).

        A run that teaches a pad (:attr:`pad`) takes ``other``'s controller instead
        (:meth:`_teach_from`)."""
        if self.pad is not None:
            return self._teach_from(other)
        src = Path(other)
        self._check_new_folder()
        try:
            theirs = json.loads((src / "profile.json").read_text())
        except (OSError, ValueError) as exc:
            raise PipelineError(f"{src}/profile.json: not a run folder's profile ({exc})") from exc
        if not isinstance(theirs, dict) or not isinstance(theirs.get("profile"), dict):
            raise PipelineError(f"{src}/profile.json: expected an object with a 'profile' object")
        prof = {**Profile.added_defaults(), **theirs["profile"]}
        mine = self.profile.to_dict()
        free = set(ESTIMATOR_KEYS) | set(LABEL_KEYS) | set(VISION_KEYS) | set(PERCEPTION_KEYS)
        differ = sorted(k for k in mine if k not in free and prof.get(k) != mine[k])
        if theirs.get("scenario") != self.scenario_path:
            differ.append("scenario")
        if differ:
            may = ESTIMATOR_KEYS + VISION_KEYS + PERCEPTION_KEYS
            raise PipelineError(
                f"--from {src}: its profile differs in {', '.join(differ)} (only estimator "
                f"settings, the perception and the vision stage's may: {', '.join(may)}"
                "); train this run from scratch"
            )
        cnn = any(prof.get(k) != mine[k] for k in PERCEPTION_KEYS)
        trained = STAGES[: STAGES.index("perception" if cnn else "vision")]
        taken = []
        for record in sorted((src / "stages").glob("*.json")):
            stage = record.stem.split("_r")[0]
            if stage in trained:
                (self.root / "stages" / record.name).write_text(record.read_text())
                taken.append(record.stem)
        missing = [s for s in trained if s not in taken]
        if missing:
            for name in taken:
                self.record_path(name).unlink()
            raise PipelineError(f"--from {src}: stages {', '.join(missing)} have not finished")
        path = self.root / "profile.json"
        data = json.loads(path.read_text())
        data["started_from"] = {"run": str(src), "commit": self.commit, "stages": taken}
        path.write_text(json.dumps(data, indent=2))
        self.say(f"started from {src}: {', '.join(taken)}")
        return taken

    def _teach_from(self, other: str | Path) -> list[str]:
        """Begin a pad run from ``other`` (a checkpoint, or a run folder's vision checkpoint):
        ``profile.json`` records it (``started_from``: checkpoint, its sha256, run, commit); the
        stages read its controller and CNN from there. Its network must be this profile's
        (estimator settings aside). Started from the same checkpoint already: nothing to do
        (a resumed run). Returns no stage: none is copied.

        Raises:
            PipelineError: not a vision checkpoint or run, another network, or this run was
                started from another checkpoint or has stages of its own."""
        from companion.files import sha256_file
        from training.pad_teach import (
            SourceRecord,
            check_source,
            read_started_from,
            source_checkpoint,
        )

        checkpoint, run = source_checkpoint(other)
        sha = sha256_file(checkpoint)
        before = read_started_from(self.root)
        if before is not None:
            if before.sha256 != sha:
                raise PipelineError(
                    f"{self.root}: this run teaches from {before.checkpoint} (sha256 "
                    f"{before.sha256[:12]}), not {checkpoint} ({sha[:12]}); use a new --out folder"
                )
            return []
        self._check_new_folder()
        check_source(checkpoint, self.net_config("vision"))
        record = SourceRecord(checkpoint=str(checkpoint), sha256=sha, run=run, commit=self.commit)
        path = self.root / "profile.json"
        data = json.loads(path.read_text())
        data["started_from"] = record.to_dict()
        path.write_text(json.dumps(data, indent=2))
        assert self.pad is not None
        self.say(
            f"teaching pad {self.pad.design.name} to the controller of {checkpoint} (the CNN is "
            f"retrained; start altitudes {self.pad.record.start_altitude_m[0]:g}-"
            f"{self.pad.record.start_altitude_m[1]:g} m)"
        )
        return []

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

    # ------------------------------------------------------------------ stage records

    def record_path(self, stage: str) -> Path:
        return self.root / "stages" / f"{stage}.json"

    def done(self, stage: str) -> StageRecord | None:
        """The record of a finished stage, None if it has not finished.

        Raises:
            PipelineError: the record is not the layout its stage writes (names the field).
        """
        path = self.record_path(stage)
        if not path.exists():
            return None
        try:
            data = json.loads(path.read_text())
        except ValueError:
            return None  # a half-written record: redo the stage
        try:
            return record_type(stage).from_dict(data, str(path))
        except RecordError as exc:
            raise PipelineError(
                f"{exc} (the stage record of another version? rerun the stage: "
                f"visland train {stage} --run {self.root} --redo)"
            ) from None

    def finish(self, record: S) -> S:
        """Write ``stages/<record.stage>.json``; returns the record as it now reads from disk."""
        data = jsonable(record.to_dict())
        path = self.record_path(record.stage)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data, indent=2))
        tmp.replace(path)
        return type(record).from_dict(data, str(path))

    def need(self, stage: str, kind: type[S]) -> S:
        """The record of ``stage``, which must have finished (:class:`PipelineError` if not)."""
        rec = self.done(stage)
        if rec is None:
            raise PipelineError(
                f"stage {stage!r} of {self.root} has not finished; run it first "
                f"(visland train {stage} --run {self.root})"
            )
        assert isinstance(rec, kind), (stage, type(rec))
        return rec

    # ------------------------------------------------------------------ helpers for stages

    def bar(self, total: int, desc: str) -> tqdm:
        return tqdm(total=total, desc=desc, file=sys.stderr, disable=not self.progress)

    def net_config(self, kind: str):
        """The ``companion.policy_net.NetConfig`` of a ``privileged`` or ``vision`` policy."""
        from training.train import net_config_for  # torch: only where a stage trains

        return net_config_for(
            self.vehicle, self.sim, kind, self.planet, **self.profile.net_options()
        )

    def metadata(self, stage: str, data: dict[str, Any]) -> dict[str, Any]:
        """What a checkpoint of ``stage`` records about how it was made."""
        return {
            "stage": stage,
            "profile": self.profile.name,
            "run": str(self.root),
            "git_commit": self.commit,
            "scenario": self.worlds.path or self.scenario_path or "configs/scenario.toml",
            "worlds": [
                {"name": w.name, "scenario": w.file, "share": w.share, "seed_offset": w.seed_offset}
                for w in self.worlds.worlds
            ]
            if self.worlds.path
            else None,
            "data": data,
            "created_unix": time.time(),
        }
