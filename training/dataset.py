"""Training data: frozen :class:`Episode` records from flight logs + expert labels, cached.

An episode is one flight log (``visland collect`` or a DAgger rollout) joined, control step by
control step (``frame_id``), with its expert labels: the ``/label/command`` topic of its
``.labels.mcap`` (``visland relabel``), or — for a flight the expert itself flew — the recorded
``/command``, which *is* the expert's label. Arrays are validated once when built and cached as
``.npz`` beside a run (keyed by the source files' size and mtime), so later stages reload a
400-episode buffer in seconds.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from companion.contract.record_base import ABSENT, TIME_S, RecordError
from companion.contract.records import (
    CommandRecord,
    GroundTruthRecord,
    LabelRecord,
    ObservationRecord,
    RawImageRecord,
)
from companion.contract.topics import (
    TOPIC_COMMAND,
    TOPIC_GROUNDTRUTH,
    TOPIC_IMAGE,
    TOPIC_LABEL,
    TOPIC_OBSERVATION,
    TOPIC_RESULT,
)
from companion.flightlog import FlightLogError, read_log

__all__ = ["DatasetError", "Episode", "load_episode", "load_episodes"]

_CACHE_VERSION = 3

R = TypeVar("R")


class DatasetError(ValueError):
    """A flight log or label file cannot become a training episode (names the file)."""


@dataclass(frozen=True)
class Episode:
    """One flight, aligned per control step (``T`` steps). Arrays are read-only.

    ``images`` is ``None`` when the flight was flown without rendering (privileged rollouts).
    ``label`` (T, 4) is the expert's command (thrust_norm, p, q, r) at each step.
    """

    name: str
    source: str
    frame_id: np.ndarray
    time_s: np.ndarray
    attitude_rad: np.ndarray
    rate_frd_rad_s: np.ndarray
    accel_frd_m_s2: np.ndarray
    range_m: np.ndarray
    pos_ned_m: np.ndarray
    """(T, 3) relative to the pad's surface centre (``GroundTruth.pad_relative``): the
    recorded position where the pad is the nominal one, at rest at the origin."""
    vel_ned_m_s: np.ndarray
    """(T, 3) relative to the pad's (likewise)."""
    quat_wxyz: np.ndarray
    label: np.ndarray
    flown: np.ndarray
    """(T, 4) the command that was actually sent (the learner's, in DAgger rollouts)."""
    image_time_s: np.ndarray | None = None
    """(T,) the Observation's image exposure time (None: a dataset built without it)."""
    attitude_time_s: np.ndarray | None = None
    """(T,) the Observation's ATTITUDE time stamp."""
    hover_thrust_norm: np.ndarray | None = None
    """(T,) the Observation's hover thrust (NaN where the log has none)."""
    range_time_s: np.ndarray | None = None
    """(T,) the Observation's radar reading time stamp (NaN where the log has none)."""
    images: np.ndarray | None = None
    result: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.frame_id.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        out = {
            k: getattr(self, k)
            for k in (
                "frame_id",
                "time_s",
                "attitude_rad",
                "rate_frd_rad_s",
                "accel_frd_m_s2",
                "range_m",
                "pos_ned_m",
                "vel_ned_m_s",
                "quat_wxyz",
                "label",
                "flown",
            )
        }
        for key in _OPTIONAL:
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        if self.images is not None:
            out["images"] = self.images
        return out


_OPTIONAL = ("image_time_s", "attitude_time_s", "hover_thrust_norm", "range_time_s")
"""Per-step arrays an Episode may lack (built by hand, e.g. in tests); NaN allowed in them."""


def _validate(ep: Episode, where: str) -> Episode:
    n = len(ep)
    if n == 0:
        raise DatasetError(f"{where}: no control steps")
    shapes = {
        "time_s": (n,),
        "attitude_rad": (n, 3),
        "rate_frd_rad_s": (n, 3),
        "accel_frd_m_s2": (n, 3),
        "range_m": (n,),
        "pos_ned_m": (n, 3),
        "vel_ned_m_s": (n, 3),
        "quat_wxyz": (n, 4),
        "label": (n, 4),
        "flown": (n, 4),
    }
    for key, shape in shapes.items():
        arr = getattr(ep, key)
        if arr.shape != shape:
            raise DatasetError(f"{where}: {key} has shape {arr.shape}, expected {shape}")
        finite = np.isfinite(arr)
        if key == "range_m":
            continue  # NaN = radar invalid, part of the contract
        if not finite.all():
            bad = int(ep.frame_id[np.argwhere(~finite)[0][0]])
            raise DatasetError(f"{where}: {key} is not finite at frame {bad}")
    for key in _OPTIONAL:
        arr = getattr(ep, key)
        if arr is not None and arr.shape != (n,):
            raise DatasetError(f"{where}: {key} has shape {arr.shape}, expected {(n,)}")
    if ep.images is not None and ep.images.shape[0] != n:
        raise DatasetError(f"{where}: {ep.images.shape[0]} images for {n} control steps")
    for arr in ep.arrays().values():
        arr.setflags(write=False)
    return ep


def _vec(records: list[Any], key: str, n: int) -> np.ndarray:
    return np.array([getattr(r, key) for r in records], dtype=float).reshape(len(records), n)


def _nan_if_none(values: list[Any]) -> np.ndarray:
    """Floats with ``None`` (null in the log) or :data:`ABSENT` (left out) as NaN."""
    return np.array([math.nan if v is None or v is ABSENT else v for v in values], dtype=float)


def _by_frame(messages: list[dict[str, Any]], record: type[R]) -> dict[int, R]:
    """Each message read as its contract ``record``, by frame id."""
    return {(r := record.from_dict(m)).frame_id: r for m in messages}  # type: ignore[attr-defined]


def _from_logs(log_path: Path, label_path: Path | None, with_images: bool) -> Episode:
    topics = [TOPIC_OBSERVATION, TOPIC_GROUNDTRUTH, TOPIC_COMMAND, TOPIC_RESULT]
    if with_images:
        topics.append(TOPIC_IMAGE)
    try:
        log = read_log(log_path, topics=topics)
    except FlightLogError as exc:
        raise DatasetError(str(exc)) from None
    meta_ep = log.metadata.get("episode", {})
    source = str(meta_ep.get("source", "unknown"))
    try:
        obs = _by_frame(log.topic(TOPIC_OBSERVATION), ObservationRecord)
        # with each step's flight time: the SITL's records carry it beside their SITL-clock stamp
        truth = {
            (r := GroundTruthRecord.from_dict(m)).frame_id: (
                r,
                float(m[TIME_S]) if r.flight_time_s is ABSENT else float(r.flight_time_s),
            )
            for m in log.topic(TOPIC_GROUNDTRUTH)
        }
        flown = _by_frame(log.topic(TOPIC_COMMAND), CommandRecord)
    except (KeyError, TypeError, RecordError) as exc:
        raise DatasetError(f"{log_path}: malformed record: {exc}") from None
    labels: dict[int, LabelRecord] | dict[int, CommandRecord]
    if label_path is not None:
        try:
            labels_log = read_log(label_path, topics=[TOPIC_LABEL])
            labels = _by_frame(labels_log.topic(TOPIC_LABEL), LabelRecord)
        except FlightLogError as exc:
            raise DatasetError(str(exc)) from None
        except (KeyError, TypeError, RecordError) as exc:
            raise DatasetError(f"{label_path}: malformed record: {exc}") from None
        where_labels = str(label_path)
    elif source == "expert":
        labels, where_labels = flown, f"{log_path} (/command, flown by the expert)"
    else:
        raise DatasetError(
            f"{log_path}: flown by {source!r}, not the expert, and no label file given "
            "(run `visland relabel` on it)"
        )
    frames = sorted(set(obs) & set(truth) & set(labels) & set(flown))
    if not frames:
        raise DatasetError(f"{log_path}: no control step has observation, ground truth and label")
    # Only the contiguous prefix: a truncated log or label file ends the sequence.
    contiguous = [frames[0]]
    for f in frames[1:]:
        if f != contiguous[-1] + 1:
            break
        contiguous.append(f)
    frames = contiguous
    o = [obs[f] for f in frames]
    t = [truth[f][0] for f in frames]
    lab = [labels[f] for f in frames]
    fl = [flown[f] for f in frames]
    images = None
    if with_images:
        image_msgs = [RawImageRecord.from_dict(m) for m in log.topic(TOPIC_IMAGE)]
        if not image_msgs:
            raise DatasetError(f"{log_path}: no camera frames (flown without rendering?)")
        _, frames_arr = log.images()
        # foxglove.RawImage frame_id is "camera/<frame id>"
        index = {int(m.frame_id.rsplit("/", 1)[-1]): i for i, m in enumerate(image_msgs)}
        missing = [f for f in frames if f not in index]
        if missing:
            raise DatasetError(f"{log_path}: no camera frame for frame {missing[0]}")
        images = frames_arr[[index[f] for f in frames]]
    try:
        ep = Episode(
            name=log_path.name,
            source=source,
            frame_id=np.array(frames, dtype=np.int64),
            time_s=np.array([truth[f][1] for f in frames], dtype=float),
            attitude_rad=_vec(o, "attitude_rad", 3),
            rate_frd_rad_s=_vec(o, "rate_frd_rad_s", 3),
            accel_frd_m_s2=_vec(o, "accel_frd_m_s2", 3),
            range_m=_nan_if_none([r.range_m for r in o]),
            pos_ned_m=_relative(t, "pos_ned_m", "pad_pos_ned_m"),
            vel_ned_m_s=_relative(t, "vel_ned_m_s", "pad_vel_ned_m_s"),
            quat_wxyz=_vec(t, "quat_wxyz", 4),
            label=np.array([[r.thrust_norm, *r.rate_frd_rad_s] for r in lab], dtype=float),
            flown=np.array([[r.thrust_norm, *r.rate_frd_rad_s] for r in fl], dtype=float),
            image_time_s=np.array([r.image_time_s for r in o], dtype=float),
            attitude_time_s=np.array([r.attitude_time_s for r in o], dtype=float),
            hover_thrust_norm=_nan_if_none([r.hover_thrust_norm for r in o]),
            range_time_s=_nan_if_none([r.range_time_s for r in o]),
            images=images,
            result=(log.topic(TOPIC_RESULT) or [{}])[-1],
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{log_path} / {where_labels}: malformed record: {exc!r}") from None
    return _validate(ep, f"{log_path}")


def _relative(truth: list[GroundTruthRecord], name: str, pad_name: str) -> np.ndarray:
    """(T, 3) the vehicle's ``name`` relative to the pad's (``pad_name``) where the record
    states the pad (a site that moves or is not flat), else as recorded (the pad at rest at
    the origin): what the vision estimator estimates, and what the controller learns from."""
    own = _vec(truth, name, 3)
    pad = [getattr(r, pad_name) for r in truth]
    if all(p is ABSENT for p in pad):
        return own
    return own - np.array([np.zeros(3) if p is ABSENT else p for p in pad], dtype=float)


def _stamp(path: Path | None) -> list[Any]:
    if path is None:
        return [None]
    st = path.stat()
    return [str(path.resolve()), st.st_size, st.st_mtime_ns]


def load_episode(
    log_path: str | Path,
    label_path: str | Path | None = None,
    with_images: bool = False,
    cache_dir: str | Path | None = None,
) -> Episode:
    """One training episode from a flight log (+ its label file). Raises :class:`DatasetError`."""
    log_path = Path(log_path)
    label_path = Path(label_path) if label_path is not None else None
    if not log_path.is_file():
        raise DatasetError(f"{log_path}: no such flight log")
    if label_path is not None and not label_path.is_file():
        raise DatasetError(f"{label_path}: no such label file (run `visland relabel`)")
    cache = None
    key = json.dumps([_CACHE_VERSION, _stamp(log_path), _stamp(label_path), with_images])
    if cache_dir is not None:
        cache = Path(cache_dir) / (log_path.stem + (".img" if with_images else "") + ".npz")
        if cache.is_file():
            try:
                with np.load(cache, allow_pickle=False) as z:
                    if str(z["key"]) == key:
                        meta = json.loads(str(z["meta"]))
                        arrays = {k: z[k] for k in z.files if k not in ("key", "meta")}
                        return _validate(Episode(**meta, **arrays), str(cache))
            except (OSError, ValueError, KeyError, TypeError, DatasetError):
                pass  # a stale or damaged cache is rebuilt from the logs
    ep = _from_logs(log_path, label_path, with_images)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(".tmp.npz")
        meta = {"name": ep.name, "source": ep.source, "result": ep.result}
        np.savez(tmp, key=np.array(key), meta=np.array(json.dumps(meta)), **ep.arrays())
        tmp.replace(cache)
    return ep


def load_episodes(
    pairs: list[tuple[Path, Path | None]],
    with_images: bool = False,
    cache_dir: str | Path | None = None,
    skip_bad: bool = True,
) -> tuple[list[Episode], list[str]]:
    """Load many; with ``skip_bad`` a bad file is reported (second list) and the rest go on."""
    episodes, errors = [], []
    for log, label in pairs:
        try:
            episodes.append(load_episode(log, label, with_images, cache_dir))
        except DatasetError as exc:
            if not skip_bad:
                raise
            errors.append(str(exc))
    return episodes, errors
