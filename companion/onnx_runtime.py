"""ONNX Runtime backend of the learned policy (``runtime = "onnx"``), and its export.

The networks run in ONNX Runtime; everything between them — the pinhole geometry, the pad
estimator (Kalman), the control features, the clamps and checks of ``act`` — is
:class:`companion.policy_net.LearnedPolicy`'s own Python code, shared with the torch path. The
export is generic over the two public modules' call contracts, not their internals:

* ``<stem>.perception.onnx`` — ``PerceptionCNN``: ``image`` (B, 128, 128) uint8 →
  ``perception`` (B, 3) float32 (tan right, tan forward, visibility logit);
* ``<stem>.control.onnx`` — one step of ``ControlLSTM``: ``features`` (B, F) float32 and its
  recurrent state ``state_in_<k>`` (the tensors of ``zero_state``, e.g. LSTM h and c, each
  (1, B, H)) → ``command`` (B, 4) (thrust_norm, p, q, r) and ``state_out_<k>``.

Both files sit beside the checkpoint they were exported from (``models/x.pt`` →
``models/x.perception.onnx``, ``models/x.control.onnx``) and carry in their metadata the
checkpoint's sha256, so a retrained checkpoint with a stale export is refused rather than flown.
The net config (estimator noise model, FOV, hover thrust...) is read from the checkpoint itself.

On the board the backend needs ``onnxruntime`` (``pip install 'visland[onnx]'``); the export
needs ``onnx`` too. Both run on the CPU, single-threaded by default (``torch_threads``).
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from companion.files import sha256_file

__all__ = [
    "ONNX_FORMAT",
    "OnnxExport",
    "OnnxModelError",
    "export_onnx",
    "load_onnx_policy",
    "onnx_paths",
]

ONNX_FORMAT = "visland-onnx"
ONNX_VERSION = 1
OPSET = 17
"""ONNX opset of the export (onnxruntime >= 1.14 runs it; 17 is what torch's TorchScript-based
exporter targets by default)."""

_INSTALL_HINT = "pip install 'visland[onnx]' (or: pip install onnxruntime onnx)"


class OnnxModelError(ValueError):
    """An ONNX export is missing, corrupt, stale (another checkpoint) or not runnable here."""


def onnx_paths(checkpoint: str | Path) -> tuple[Path, Path]:
    """The export's (perception, control) files for ``checkpoint`` (beside it, same stem)."""
    ckpt = Path(checkpoint)
    return (
        ckpt.with_name(ckpt.stem + ".perception.onnx"),
        ckpt.with_name(ckpt.stem + ".control.onnx"),
    )


# --------------------------------------------------------------------------- export


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
        return dict(self.__dict__)


def _onnx_bytes(module: nn.Module, args: tuple, inputs, outputs, dynamic) -> bytes:
    import io

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
        raise OnnxModelError(f"export to ONNX needs {exc.name}: {_INSTALL_HINT}") from None
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
            images = torch.from_numpy(
                rng.integers(0, 256, (check_samples, size, size), dtype=np.uint8)
            )
            ref = policy.perception(images).numpy()
            got = onnx_policy.perception(images).numpy()
            # the visibility logit reaches hundreds on noise images: compare its float32
            # digits, not its absolute size (absolute below 1, relative above)
            pdiff = float(np.max(np.abs(ref - got) / np.maximum(1.0, np.abs(ref))))
        feats = torch.from_numpy(
            rng.normal(0.0, 1.0, (1, check_samples, len(names))).astype(np.float32)
        )
        ref_cmd, _ = policy.control(feats, policy.control.zero_state(1))
        got_cmd, _ = onnx_policy.control(feats, onnx_policy.control.zero_state(1))
        cdiff = float(np.max(np.abs(ref_cmd.numpy() - got_cmd.numpy())))
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


# --------------------------------------------------------------------------- runtime


def _session(path: Path, role: str, ckpt: Path, sha: str, threads: int):
    """An ONNX Runtime CPU session of ``path``, checked to be ``role`` of checkpoint ``ckpt``
    (whose sha256 is ``sha``)."""
    import onnxruntime as ort

    if not path.is_file():
        raise OnnxModelError(
            f"{path}: no such ONNX file; export it with `visland export-onnx --checkpoint {ckpt}`"
        )
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(1, threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # errors only: they come back as exceptions anyway
    try:
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own Fail/InvalidProtobuf/... types
        raise OnnxModelError(
            f"{path}: not a loadable ONNX model ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0][:200]})"
        ) from None
    meta = sess.get_modelmeta().custom_metadata_map
    if meta.get("visland.format") != ONNX_FORMAT or meta.get("visland.role") != role:
        raise OnnxModelError(
            f"{path}: not a visland {role} export (metadata visland.format/role = "
            f"{meta.get('visland.format')!r}/{meta.get('visland.role')!r}); re-run visland "
            "export-onnx"
        )
    if meta.get("visland.version") != str(ONNX_VERSION):
        raise OnnxModelError(
            f"{path}: export version {meta.get('visland.version')!r}, this code reads "
            f"{ONNX_VERSION}; re-run visland export-onnx"
        )
    if meta.get("visland.checkpoint_sha256") != sha:
        raise OnnxModelError(
            f"{path}: exported from another checkpoint (sha256 "
            f"{str(meta.get('visland.checkpoint_sha256'))[:12]}…, the checkpoint now is "
            f"{sha[:12]}…): a stale export; re-run visland export-onnx --checkpoint {ckpt}"
        )
    return sess, meta


class _OnnxPerception(nn.Module):
    """Stands in for ``PerceptionCNN`` inside a ``LearnedPolicy``: same call, ONNX Runtime."""

    def __init__(self, session, path: Path) -> None:
        super().__init__()
        self._sess = session
        self.path = path

    def forward(self, image_u8: torch.Tensor) -> torch.Tensor:
        """``image_u8``: (B, H, W) or (B, 1, H, W), uint8 (or float in [0, 255]). (B, 3)."""
        x = image_u8.detach().cpu()
        if x.dim() == 4:
            x = x[:, 0]
        arr = np.ascontiguousarray(x.numpy())
        if arr.dtype != np.uint8:
            arr = np.clip(np.rint(arr), 0, 255).astype(np.uint8)
        (out,) = self._sess.run(["perception"], {"image": arr})
        return torch.from_numpy(out)


class _OnnxControl(nn.Module):
    """Stands in for ``ControlLSTM``: ``forward(features (B, T, F), state)`` and
    ``zero_state(batch)``, one ONNX Runtime call per time step."""

    def __init__(self, session, path: Path, control: nn.Module) -> None:
        super().__init__()
        self._sess = session
        self.path = path
        self._zero = tuple(z.detach().clone() for z in control.zero_state(1))
        self._batch_axis = _batch_axes(control)
        self._n = len(self._zero)
        self._outputs = ["command", *(f"state_out_{k}" for k in range(self._n))]

    def zero_state(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        return tuple(
            z.repeat_interleave(batch, dim=a[0]) if batch != 1 and a else z.clone()
            for z, a in zip(self._zero, self._batch_axis, strict=True)
        )

    def forward(self, features: torch.Tensor, state=None):
        """``features`` (B, T, F) -> commands (B, T, 4), next state (as ControlLSTM)."""
        if state is None:
            state = self.zero_state(features.shape[0])
        feats = features.detach().cpu().numpy().astype(np.float32, copy=False)
        st = [np.ascontiguousarray(s.detach().cpu().numpy(), dtype=np.float32) for s in state]
        outs = []
        for t in range(feats.shape[1]):
            feed = {"features": np.ascontiguousarray(feats[:, t])}
            feed.update({f"state_in_{k}": s for k, s in enumerate(st)})
            res = self._sess.run(self._outputs, feed)
            outs.append(res[0])
            st = res[1:]
        return (
            torch.from_numpy(np.stack(outs, axis=1)),
            tuple(torch.from_numpy(s) for s in st),
        )


def load_onnx_policy(checkpoint: str | Path, threads: int = 1):
    """The checkpoint's policy with its networks run by ONNX Runtime (CPU, ``threads``
    intra-op threads): a :class:`companion.policy_net.LearnedPolicy` whose geometry, estimator
    and ``act`` are the torch path's own code.

    Raises:
        companion.policy_net.CheckpointError: the checkpoint is not readable.
        OnnxModelError: onnxruntime is not installed, or an ONNX file is missing, corrupt or
            exported from another checkpoint (each names the file and the fix).
    """
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        raise OnnxModelError(f"runtime = 'onnx' needs onnxruntime: {_INSTALL_HINT}") from None
    from companion.policy_net import LearnedPolicy, load_policy

    ckpt = Path(checkpoint)
    torch_policy = load_policy(ckpt)  # config, metadata, and the CheckpointError checks
    sha = sha256_file(ckpt)
    perception_path, control_path = onnx_paths(ckpt)
    control_sess, meta = _session(control_path, "control", ckpt, sha, threads)
    zero = tuple(torch_policy.control.zero_state(1))
    if meta.get("visland.state_count") != str(len(zero)):
        raise OnnxModelError(
            f"{control_path}: {meta.get('visland.state_count')} state tensors, the network has "
            f"{len(zero)}; re-run visland export-onnx"
        )
    control = _OnnxControl(control_sess, control_path, torch_policy.control)
    perception = None
    if torch_policy.perception is not None:
        perception_sess, _ = _session(perception_path, "perception", ckpt, sha, threads)
        perception = _OnnxPerception(perception_sess, perception_path)
    metadata = {**torch_policy.metadata, "runtime": "onnx", "onnx": str(control_path)}
    return LearnedPolicy(torch_policy.config, control, perception, metadata)
