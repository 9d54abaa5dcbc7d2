"""Policy checkpoints (torch): writing them, and loading them as networks or a policy.

A checkpoint is a plain ``torch.save`` dict of tensors and JSON-able values, loaded with
``weights_only=True`` (no code runs on load); it carries its network config, the feature
names, training provenance and git commit.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from companion.policy_net.config import CheckpointError, NetConfig
from companion.policy_net.geometry import feature_names
from companion.policy_net.networks import ControlLSTM, PerceptionCNN
from companion.policy_net.policy import LearnedPolicy

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "load_networks",
    "load_policy",
    "save_checkpoint",
    "untrained_policy",
]

CHECKPOINT_FORMAT = "visland-policy"
CHECKPOINT_VERSION = 1


def save_checkpoint(
    path: str | Path,
    config: NetConfig,
    control: ControlLSTM,
    perception: PerceptionCNN | None,
    metadata: dict[str, Any],
) -> Path:
    """Write a checkpoint atomically (``.tmp`` then rename). ``metadata``: JSON-able values."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "net_config": config.to_dict(),
        "feature_names": list(feature_names(config.hover_input)),
        "control": control.state_dict(),
        "perception": perception.state_dict() if perception is not None else None,
        "metadata": metadata,
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(blob, tmp)
    tmp.replace(path)
    return path


def _load_blob(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a damaged zip/pickle
        raise CheckpointError(
            f"{path}: not a readable visland checkpoint ({type(exc).__name__}: {exc})"
        ) from None
    if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"{path}: not a visland policy checkpoint (expected format {CHECKPOINT_FORMAT!r})"
        )
    if blob.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint version {blob.get('version')!r}, this code reads "
            f"{CHECKPOINT_VERSION}"
        )
    return blob


def load_networks(path: str | Path) -> tuple[NetConfig, ControlLSTM, PerceptionCNN | None, dict]:
    """The checkpoint's config and networks (for training to continue from)."""
    path = Path(path)
    blob = _load_blob(path)
    try:
        cfg = NetConfig.from_dict(dict(blob["net_config"]))
    except (TypeError, KeyError) as exc:
        raise CheckpointError(f"{path}: net_config: {exc}") from None
    except CheckpointError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    expected = list(feature_names(cfg.hover_input))
    if list(blob.get("feature_names", [])) != expected:
        raise CheckpointError(
            f"{path}: feature_names {blob.get('feature_names')!r} differ from this code's "
            f"controller inputs {expected!r}"
        )
    control = ControlLSTM(cfg)
    perception = PerceptionCNN(cfg) if blob.get("perception") is not None else None
    try:
        control.load_state_dict(blob["control"])
        if perception is not None:
            perception.load_state_dict(blob["perception"])
    except (RuntimeError, KeyError, TypeError) as exc:
        raise CheckpointError(f"{path}: weights do not fit the network: {exc}") from None
    for name, module in (("control", control), ("perception", perception)):
        if module is None:
            continue
        for pname, p in module.state_dict().items():
            if not torch.all(torch.isfinite(p)):
                raise CheckpointError(f"{path}: {name}.{pname} holds non-finite values")
    return cfg, control, perception, dict(blob.get("metadata") or {})


def load_policy(path: str | Path) -> LearnedPolicy:
    """Load a checkpoint as a ready-to-fly policy. Raises :class:`CheckpointError`."""
    cfg, control, perception, meta = load_networks(path)
    if cfg.kind == "vision" and perception is None:
        raise CheckpointError(f"{path}: vision policy without perception weights")
    return LearnedPolicy(cfg, control, perception if cfg.kind == "vision" else None, meta)


def untrained_policy(seed: int = 0, privileged: bool = False) -> LearnedPolicy:
    """A randomly initialised policy of the shipped size (for tests and latency benchmarks)."""
    torch.manual_seed(seed)
    cfg = NetConfig(kind="privileged" if privileged else "vision")
    return LearnedPolicy(
        cfg, ControlLSTM(cfg), None if privileged else PerceptionCNN(cfg), {"untrained": True}
    )
