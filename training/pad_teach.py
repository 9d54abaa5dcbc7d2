"""Teach a pad: a run that keeps a trained policy's controller and retrains its CNN on frames
rendered with a new pad (``visland pipeline --profile P --pad PADFILE --from RUN --out DIR``).

The estimator and the controller work on the pad's bearing and the radar's range, which do not
depend on what the pad looks like; only the CNN does. So a pad run

- takes the controller of ``--from`` (a run folder's ``vision`` checkpoint, or a shipped model
  such as ``models/visland_vision.pt``: a checkpoint carries its config and both networks);
- flies the profile's worlds (its worlds file, or its one scenario) with ``[pad] design`` set to
  the new pad and every ``[initial_state] altitude_m`` scaled to the pad's envelope — the start
  altitudes of :func:`sitl_sim.render.pads.start_altitudes_m` (the rule of ``visland pad info``):
  the paper's 75-100 m for its 4 m pad become 18.75-25 m for a 1 m one. The derived scenario
  files are written into the run folder (``worlds/``), so every stage and process reads them;
- runs the stages ``perception`` (pose-sampled frames rendered in those worlds with the new pad,
  at altitudes scaled the same way; the CNN fine-tuned from the ``--from`` model's), ``vision``
  (the ``--from`` controller fed by the new CNN, its estimator's lowest horizontal fix
  ``min_fix_altitude_m`` scaled the same way, scored on the validation seeds; vision DAgger
  rounds only when that score misses :data:`PAD_VALIDATION_SUCCESS`) and ``eval`` (the pad's
  suite, :func:`pad_suite_text`, flown by the taught model and by the ``--from`` model, on the
  evaluation seed) — ``training.stages.teach``;
- writes ``pad_metrics.json`` (:class:`PadMetrics`); ``visland ship --run DIR`` ships
  ``models/visland_vision_<pad>.pt`` with its own card (``training.ship_pad``).

The pad's suite is the standard suite's ``nominal``, ``low_sun``, ``unseen_terrain`` and
``wind_moderate_gusts`` conditions with the same two changes. ``configs/suites/helipad_1m.toml`` is
this module's output for the shipped 1 m helipad (``python -m training.pad_teach
configs/pads/helipad_1m.toml > configs/suites/helipad_1m.toml``; a test holds it to the code).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.files import sha256_file
from companion.table import section_dict
from sitl_sim.config import CameraConfig, load_sim
from sitl_sim.render.pads import (
    REFERENCE,
    PadDesign,
    builtin_pad_paths,
    load_pad,
    start_altitudes_m,
)
from sitl_sim.scenario import SECTIONS, Scenario
from training.profiles import PipelineError, Profile
from training.provenance import MODEL_NAME, REPO
from training.record import Record
from training.seeds import EVAL_SEED
from training.stage_records import PerceptionRecord, VisionRecord
from training.worlds import WorldMix, load_worlds

__all__ = [
    "PAD_STAGES",
    "PAD_SUITE_CONDITIONS",
    "PAD_SUITE_EPISODES",
    "PAD_VALIDATION_SUCCESS",
    "PadMetrics",
    "PadRecord",
    "PadTeach",
    "SourceRecord",
    "file_text",
    "pad_suite_text",
    "pad_worlds",
    "teach_pad",
    "toml_text",
]

PAD_STAGES = ("perception", "vision", "eval")
"""The stages of a pad run (the controller's stages are the ``--from`` model's)."""

PAD_SUITE_CONDITIONS = ("nominal", "low_sun", "unseen_terrain", "wind_moderate_gusts")
"""The conditions of ``configs/suites/standard.toml`` a pad's suite flies."""

PAD_SUITE_EPISODES = 50
"""Episodes per condition of a pad's suite (fewer where the profile evaluates fewer)."""

PAD_VALIDATION_SUCCESS = 0.98
"""The validation success rate the ``--from`` controller must reach with the new CNN; below it
the ``vision`` stage flies the profile's vision DAgger rounds."""

STANDARD_SUITE = REPO / "configs" / "suites" / "standard.toml"


@dataclass(frozen=True)
class PadRecord(Record):
    """The pad a run teaches, as ``profile.json`` and ``pad_metrics.json`` record it."""

    name: str
    file: str
    sha256: str
    size_m: tuple[float, float]
    width_m: float
    """The pad's smaller side: what its envelope is computed from."""
    start_altitude_m: tuple[float, float]
    """:func:`sitl_sim.render.pads.start_altitudes_m` of ``width_m`` for the run's camera."""
    altitude_scale: float
    """The factor on every altitude of the profile's worlds (and of the pose sampling): the
    pad's top start altitude over the paper pad's."""


@dataclass(frozen=True)
class SourceRecord(Record):
    """The model a pad run takes its controller from (``--from``)."""

    checkpoint: str
    sha256: str
    run: str | None
    """The run folder given as ``--from`` (None: a checkpoint file was)."""
    commit: str
    """The commit that started the pad run."""


@dataclass(frozen=True)
class PadMetrics(Record):
    """``pad_metrics.json``: what the eval stage of a pad run measured."""

    profile: Profile
    git_commit: str
    pad: PadRecord
    source: SourceRecord
    eval_seed: int
    suite: str
    """The pad's suite file (``<run>/suite.toml``)."""
    report: str
    """The taught model's suite report (``suite.json``)."""
    baseline: str
    """The ``--from`` model's report on the same episodes (``suite_baseline.json``)."""
    timing: dict[str, Any]
    perception: PerceptionRecord
    vision: VisionRecord


@dataclass(frozen=True)
class PadTeach:
    """The pad a run teaches, loaded and checked, with its envelope for ``camera``."""

    design: PadDesign
    file: Path
    record: PadRecord

    @property
    def scale(self) -> float:
        return self.record.altitude_scale

    @property
    def design_text(self) -> str:
        """How a scenario names the pad: a shipped pad by its name, a file in the repository
        relative to its root, any other by its absolute path."""
        shipped = builtin_pad_paths()
        if shipped.get(self.design.name) == self.file:
            return self.design.name
        return file_text(self.file)


def teach_pad(spec: str | Path, camera: CameraConfig | None = None) -> PadTeach:
    """The pad file ``spec`` (or a shipped pad's name) with its envelope for ``camera``
    (default: the sim config's).

    Raises:
        ConfigError: naming the file: not found, not a pad file (``load_pad``'s errors), or a
            name that cannot name a model file.
    """
    from sitl_sim.errors import ConfigError

    text = str(spec)
    shipped = builtin_pad_paths()
    path = shipped[text] if text in shipped and not Path(text).exists() else Path(text)
    design = load_pad(path)
    if not MODEL_NAME.match(design.name):
        raise ConfigError(
            f"{path}: name = {design.name!r}; a taught pad names its model file "
            "(visland_vision_<name>.pt): expected letters, digits, '_', '-' or '.'"
        )
    camera = camera or load_sim().camera
    width = float(min(design.size_m))
    fov, px = camera.fov_deg, camera.width_px
    start = start_altitudes_m(width, fov, px)
    scale = start[1] / start_altitudes_m(REFERENCE["pad_m"], fov, px)[1]
    record = PadRecord(
        name=design.name,
        file=str(path.resolve()),
        sha256=sha256_file(path),
        size_m=design.size_m,
        width_m=width,
        start_altitude_m=start,
        altitude_scale=scale,
    )
    return PadTeach(design=design, file=path.resolve(), record=record)


def file_text(path: Path) -> str:
    """A file as a scenario names it: relative to the repository root when inside it (a
    scenario's relative path falls back to the root), else absolute."""
    path = Path(path).resolve()
    try:
        return path.relative_to(REPO).as_posix()
    except ValueError:
        return str(path)


def pad_scenario_table(scenario: Scenario, teach: PadTeach) -> dict[str, Any]:
    """``scenario`` as a scenario table with ``[pad] design`` the taught pad (a rover's or a
    deck's pad keeps its motion) and its altitudes scaled by ``teach.scale``; the files it
    names (ground pictures) by paths that resolve from anywhere (:func:`file_text`)."""
    table: dict[str, Any] = {"initial_state": section_dict(scenario)}
    lo, hi = scenario.altitude_m
    table["initial_state"]["altitude_m"] = [lo * teach.scale, hi * teach.scale]
    table["world"] = {"planet": scenario.world.name}
    for name in SECTIONS[2:]:
        section = getattr(scenario, name)
        if section is not None and name != "pad":
            table[name] = section_dict(section, drop_none=True)
    visual = scenario.visual
    if visual is not None and visual.ground_paths:
        table["visual"]["ground_image"] = [file_text(p) for p in visual.ground_paths]
    # a carried pad keeps its carrier (a rover, a deck): only the design changes
    pad = scenario.pad
    keep = {} if pad is None or pad.still_on_ground else section_dict(pad, drop_none=True)
    keep.pop("design", None)
    table["pad"] = {"design": [teach.design_text], **keep}
    return table


def pad_worlds(worlds: WorldMix, teach: PadTeach, folder: Path) -> WorldMix:
    """The run's worlds for the taught pad: every world's scenario with the pad and scaled
    altitudes (:func:`pad_scenario_table`) written to ``folder/<world>.toml``, and a worlds file
    ``folder/worlds.toml`` naming them with the same shares, in the same order (so each world
    flies the seeds it flew), read back by :func:`training.worlds.load_worlds`."""
    folder.mkdir(parents=True, exist_ok=True)
    tables = {}
    for w in worlds.worlds:
        name = w.name or "scenario"
        path = folder / f"{name}.toml"
        head = (
            f"# {w.file or 'configs/scenario.toml'} with [pad] design = {teach.design_text!r} and "
            f"its altitudes x {teach.scale:g} (training.pad_teach)\n"
        )
        _write(path, head + toml_text(pad_scenario_table(w.scenario, teach)))
        tables[name] = {"scenario": str(path.resolve()), "share": w.share}
    worlds_file = folder / "worlds.toml"
    head = f"# the worlds of {worlds.path or 'the run'} for pad {teach.design.name}\n"
    _write(worlds_file, head + toml_text({"worlds": tables}))
    return load_worlds(worlds_file)


def _write(path: Path, text: str) -> None:
    """``text`` into ``path``, unless it holds it already (a resumed run rewrites nothing)."""
    if path.exists() and path.read_text() == text:
        return
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def pad_suite_text(teach: PadTeach, episodes: int = PAD_SUITE_EPISODES) -> str:
    """The pad's suite file: :data:`PAD_SUITE_CONDITIONS` of the standard suite with the pad
    and its altitudes (:func:`pad_scenario_table`), ``episodes`` per condition on the
    evaluation seed."""
    from training.suite import load_suite

    standard = {c.name: c.scenario for c in load_suite(STANDARD_SUITE).conditions}
    lo, hi = teach.record.start_altitude_m
    head = (
        f"# The suite of pad {teach.design.name} ({file_text(teach.file)}, "
        f"{teach.record.width_m:g} m wide): the conditions\n"
        f"# {', '.join(PAD_SUITE_CONDITIONS)} of configs/suites/standard.toml\n"
        "# with [pad] design set and the start altitudes scaled to the pad's envelope\n"
        f"# (x {teach.scale:g}: {lo:g}-{hi:g} m, `visland pad info`). Written by "
        "training/pad_teach.py:\n"
        f"#   python -m training.pad_teach {file_text(teach.file)}\n"
        "# Fly it: visland eval --suite <this file> --policy "
        f"models/visland_vision_{teach.design.name}.pt\n\n"
    )
    data = {
        "suite": {"episodes": episodes, "seed": EVAL_SEED},
        "conditions": {
            name: {"scenario": pad_scenario_table(standard[name], teach)}
            for name in PAD_SUITE_CONDITIONS
        },
    }
    return head + toml_text(data)


def toml_text(data: dict[str, Any], prefix: tuple[str, ...] = ()) -> str:
    """``data`` (tables of numbers, strings, booleans and flat lists of them) as TOML: each
    table's values, then its sub-tables as ``[a.b.c]`` headers; lists on one line."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    out = ""
    if lines:
        out = ("[" + ".".join(prefix) + "]\n" if prefix else "") + "\n".join(lines) + "\n"
    for k, v in data.items():
        if isinstance(v, dict):
            sub = toml_text(v, (*prefix, k))
            out += ("\n" if out and sub else "") + sub
    return out


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML value for {value!r}")


def write_pad_suite(teach: PadTeach, path: Path, episodes: int) -> Path:
    """:func:`pad_suite_text` into ``path`` (kept when it holds the same text)."""
    _write(path, pad_suite_text(teach, episodes))
    return path


def read_started_from(root: Path) -> SourceRecord | None:
    """The ``started_from`` of a pad run's ``profile.json`` (None: not started yet)."""
    data = json.loads((root / "profile.json").read_text())
    src = data.get("started_from")
    if not isinstance(src, dict) or "checkpoint" not in src:
        return None
    return SourceRecord.from_dict(src, str(root / "profile.json"))


def source_checkpoint(other: str | Path) -> tuple[Path, str | None]:
    """The checkpoint ``--from`` names: a checkpoint file as is, or a run folder's ``vision``
    checkpoint (its ``stages/vision.json``); and the run folder (None for a file).

    Raises:
        PipelineError: neither, or a run whose vision stage has not finished.
    """
    src = Path(other)
    if src.is_file():
        return src, None
    record = src / "stages" / "vision.json"
    if not record.is_file():
        raise PipelineError(
            f"--from {src}: expected a checkpoint file (.pt) or a run folder whose vision stage "
            f"has finished ({record} not found)"
        )
    try:
        checkpoint = Path(VisionRecord.from_dict(json.loads(record.read_text())).checkpoint)
    except ValueError as exc:
        raise PipelineError(f"{record}: not a vision stage record ({exc})") from None
    return checkpoint, str(src)


def check_source(checkpoint: Path, mine: Any) -> None:
    """``checkpoint`` can carry this profile's vision policy: every :class:`NetConfig` field
    but the estimator's (which a run may change) is the profile's ``mine``.

    Raises:
        PipelineError: naming the fields that differ, or an unreadable checkpoint.
    """
    from dataclasses import fields

    from companion.policy_net import ESTIMATOR_FIELDS, CheckpointError, load_networks

    try:
        cfg, _, cnn, _ = load_networks(checkpoint)
    except CheckpointError as exc:
        raise PipelineError(f"--from {checkpoint}: {exc}") from None
    if cnn is None or cfg.kind != "vision":
        raise PipelineError(f"--from {checkpoint}: not a vision policy (no CNN)")
    differ = [
        f"{f.name} {getattr(cfg, f.name)!r} (profile: {getattr(mine, f.name)!r})"
        for f in fields(cfg)
        if f.name not in ESTIMATOR_FIELDS and getattr(cfg, f.name) != getattr(mine, f.name)
    ]
    if differ:
        raise PipelineError(
            f"--from {checkpoint}: its network differs from the profile's in "
            f"{'; '.join(differ)}; teach the pad with the profile it was trained with"
        )


def _main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m training.pad_teach PADFILE  (prints the pad's suite)")
        return 2
    sys.stdout.write(pad_suite_text(teach_pad(args[0])))
    return 0


if __name__ == "__main__":
    sys.exit(_main())
