"""Export a checkpoint's networks to ONNX for the board runtime (``visland export-onnx``).

Writes ``<stem>.perception.onnx`` and ``<stem>.control.onnx`` beside the checkpoint (the call
contracts are in :mod:`companion.onnx_runtime`), with the metadata the torch-free loader needs:
format and version, role, the checkpoint's sha256, net config, feature names and metadata, the
state count. Then checks that ONNX Runtime, through that very loader, gives torch's outputs.

Needs torch, ``onnx`` and ``onnxruntime`` (the ``[train]`` extra): run it where the model was
trained and copy the three files to the board.
"""

from __future__ import annotations

import io
import json
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from companion.files import sha256_file
from companion.onnx_runtime import (
    ONNX_FORMAT,
    ONNX_VERSION,
    OnnxModelError,
    load_onnx_policy,
    onnx_paths,
)

__all__ = ["OPSET", "OnnxExport", "export_onnx"]

OPSET = 17
"""ONNX opset of the export (onnxruntime >= 1.14 runs it; 17 is what torch's TorchScript-based
exporter targets by default)."""


class _ControlStep(nn.Module):
    """One step of a ControlLSTM-like module: ``(features (B, F), *state) -> (command, *state)``.

    Written against the module's public contract only: ``forward(features (B, T, F), state)``
    returns ``(commands (B, T, 4), state)`` with ``state`` a tuple of tensors.
    """

    def __init__(self, control: nn.Module) -> None:
        super().__init__()
        self.control = control

    def forward(self, features: torch.Tensor, *state: torch.Tensor):
        out, new_state = self.control(features[:, None, :], tuple(state))  # (B, 1, 4)
        return (out[:, 0], *new_state)


def _batch_axes(control: nn.Module) -> list[list[int]]:
    """Per state tensor, its batch axes: those that are 1 in ``zero_state(1)`` and 2 in
    ``zero_state(2)`` (axis 1 for torch's LSTM state (layers, B, H))."""
    one, two = tuple(control.zero_state(1)), tuple(control.zero_state(2))
    return [
        [a for a in range(x.dim()) if x.shape[a] != y.shape[a]]
        for x, y in zip(one, two, strict=True)
    ]


@dataclass(frozen=True)
class OnnxExport:
    """What :func:`export_onnx` wrote and how closely ONNX Runtime reproduces torch on it."""

    checkpoint: str
    checkpoint_sha256: str
    perception: str | None
    control: str
    opset: int
    perception_max_rel_diff: float | None
    control_max_abs_diff: float
    check_samples: int

    def to_dict(self) -> dict[str, Any]:
        """The ``--json`` document: every field, in declaration order."""
        return asdict(self)


def _onnx_bytes(module: nn.Module, args: tuple, inputs, outputs, dynamic) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings():
        # dynamo=False: the TorchScript-based exporter needs only `onnx`; the torch.export one
        # would also need onnxscript. It is deprecated in torch 2.9+ but exports these two
        # small graphs exactly (checked below against torch on random inputs).
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.filterwarnings("ignore", message=".*batch_size other than 1.*LSTM")
        # nn.LSTM's shape checks are Python ifs: traced as constants, right for these shapes
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(
            module,
            args,
            buf,
            dynamo=False,
            opset_version=OPSET,
            input_names=list(inputs),
            output_names=list(outputs),
            dynamic_axes=dynamic,
            do_constant_folding=True,
        )
    return buf.getvalue()


def _finish(raw: bytes, path: Path, props: dict[str, str]) -> None:
    """Attach the metadata, check the model, write atomically."""
    import onnx

    model = onnx.load_from_string(raw)
    onnx.helper.set_model_props(model, props)
    onnx.checker.check_model(model)
    tmp = path.with_name(path.name + ".tmp")
    onnx.save(model, tmp)
    os.replace(tmp, path)


def export_onnx(
    checkpoint: str | Path, check_samples: int = 64, seed: int = 0, tolerance: float = 1e-4
) -> OnnxExport:
    """Export ``checkpoint``'s networks to ONNX beside it (see the module doc), then check that
    ONNX Runtime gives torch's outputs on ``check_samples`` random images and a
    ``check_samples``-step rollout of random features (max difference ≤ ``tolerance``: absolute
    for the commands, relative to ``max(1, |value|)`` for the CNN outputs).

    Raises:
        companion.policy_net.CheckpointError: not a readable checkpoint.
        OnnxModelError: onnx/onnxruntime missing, or the exported graphs disagree with torch.
    """
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError as exc:
        raise OnnxModelError(
            f"export to ONNX needs {exc.name}: pip install 'visland[train]' (onnx, onnxruntime)"
        ) from None
    from companion.policy_net import feature_names, load_policy

    ckpt = Path(checkpoint)
    policy = load_policy(ckpt)
    sha = sha256_file(ckpt)
    perception_path, control_path = onnx_paths(ckpt)
    cfg = policy.config
    names = feature_names(cfg.hover_input)
    base = {
        "visland.format": ONNX_FORMAT,
        "visland.version": str(ONNX_VERSION),
        "visland.checkpoint_sha256": sha,
        "visland.checkpoint_name": ckpt.name,
        "visland.net_config": json.dumps(cfg.to_dict()),
        "visland.feature_names": json.dumps(list(names)),
        "visland.checkpoint_metadata": json.dumps(policy.metadata, default=str),
        "visland.torch_version": torch.__version__,
    }
    rng = np.random.default_rng(seed)
    size = cfg.image_size_px

    pdiff = None
    if policy.perception is not None:
        image = torch.zeros(1, size, size, dtype=torch.uint8)
        raw = _onnx_bytes(
            policy.perception,
            (image,),
            ["image"],
            ["perception"],
            {"image": {0: "batch"}, "perception": {0: "batch"}},
        )
        _finish(raw, perception_path, {**base, "visland.role": "perception"})
    elif perception_path.exists():
        perception_path.unlink()  # a privileged checkpoint has no CNN: no stale file beside it

    state = tuple(policy.control.zero_state(1))
    n_state = len(state)
    s_in = [f"state_in_{k}" for k in range(n_state)]
    s_out = [f"state_out_{k}" for k in range(n_state)]
    features = torch.zeros(1, len(names))
    dynamic = {"features": {0: "batch"}, "command": {0: "batch"}}
    for k, axes in enumerate(_batch_axes(policy.control)):
        dynamic[s_in[k]] = {a: "batch" for a in axes}
        dynamic[s_out[k]] = {a: "batch" for a in axes}
    raw = _onnx_bytes(
        _ControlStep(policy.control).eval(),
        (features, *state),
        ["features", *s_in],
        ["command", *s_out],
        dynamic,
    )
    _finish(
        raw,
        control_path,
        {**base, "visland.role": "control", "visland.state_count": str(n_state)},
    )

    # check: the files just written, through the same loader the companion uses
    onnx_policy = load_onnx_policy(ckpt, threads=1)
    with torch.inference_mode():
        if policy.perception is not None:
            images = rng.integers(0, 256, (check_samples, size, size), dtype=np.uint8)
            ref = policy.perception(torch.from_numpy(images)).numpy()
            got = onnx_policy.perceive_batch(images)
            # the visibility logit reaches hundreds on noise images: compare its float32
            # digits, not its absolute size (absolute below 1, relative above)
            pdiff = float(np.max(np.abs(ref - got) / np.maximum(1.0, np.abs(ref))))
        feats = rng.normal(0.0, 1.0, (check_samples, len(names))).astype(np.float32)
        ref_cmd, _ = policy.control(torch.from_numpy(feats)[None], policy.control.zero_state(1))
        got_cmd = onnx_policy.control_sequence(feats)
        cdiff = float(np.max(np.abs(ref_cmd[0].numpy() - got_cmd)))
    worst = max(cdiff, pdiff or 0.0)
    if not worst <= tolerance:
        raise OnnxModelError(
            f"{ckpt}: the ONNX export differs from torch by {worst:.3g} (> {tolerance}); "
            f"perception {pdiff}, control {cdiff}"
        )
    return OnnxExport(
        checkpoint=str(ckpt),
        checkpoint_sha256=sha,
        perception=str(perception_path) if policy.perception is not None else None,
        control=str(control_path),
        opset=OPSET,
        perception_max_rel_diff=pdiff,
        control_max_abs_diff=cdiff,
        check_samples=check_samples,
    )
