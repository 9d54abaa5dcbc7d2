"""ONNX Runtime backend of the learned policy (``runtime = "onnx"``): the board runtime, no torch.

The networks run in ONNX Runtime; everything between them — the pinhole geometry, the pad
estimator (Kalman), the control features, the clamps and checks of ``act`` — is
:class:`companion.policy_net.PolicyCore`'s own Python code, shared with the torch path. The
graphs (written by :func:`companion.onnx_export.export_onnx`, ``visland export-onnx``):

* ``<stem>.perception.onnx`` — ``PerceptionCNN``: ``image`` (B, 128, 128) uint8 →
  ``perception`` (B, 3) float32 (tan right, tan forward, visibility logit);
* ``<stem>.control.onnx`` — one step of ``ControlLSTM``: ``features`` (B, F) float32 and its
  recurrent state ``state_in_<k>`` (zeros at the start of a flight, e.g. LSTM h and c, each
  (1, B, H)) → ``command`` (B, 4) (thrust_norm, p, q, r) and ``state_out_<k>``.

Both files sit beside the checkpoint they were exported from (``models/x.pt`` →
``models/x.perception.onnx``, ``models/x.control.onnx``). Their metadata carries everything the
policy needs besides the weights — the checkpoint's net config (estimator noise model, FOV,
hover-thrust input...), its feature names and metadata — and the checkpoint's sha256: the
checkpoint file is hashed, never unpickled, so a retrained checkpoint with a stale export is
refused rather than flown, and no torch is needed (``pip install 'visland[companion]'``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from companion.files import sha256_file
from companion.policy_net.config import CheckpointError, NetConfig
from companion.policy_net.core import PolicyCore
from companion.policy_net.geometry import feature_names

__all__ = [
    "ONNX_FORMAT",
    "ONNX_VERSION",
    "OnnxModelError",
    "OnnxPolicy",
    "load_onnx_policy",
    "onnx_paths",
]

ONNX_FORMAT = "visland-onnx"
ONNX_VERSION = 2
"""Version of the export's metadata (2: the checkpoint's metadata travels too; the loader reads
the net config from the graphs, not from the checkpoint)."""

INSTALL_HINT = "pip install 'visland[onnx]' (or: pip install onnxruntime)"


class OnnxModelError(ValueError):
    """An ONNX export is missing, corrupt, stale (another checkpoint) or not runnable here."""


def onnx_paths(checkpoint: str | Path) -> tuple[Path, Path]:
    """The export's (perception, control) files for ``checkpoint`` (beside it, same stem)."""
    ckpt = Path(checkpoint)
    return (
        ckpt.with_name(ckpt.stem + ".perception.onnx"),
        ckpt.with_name(ckpt.stem + ".control.onnx"),
    )


def _session(path: Path, role: str, ckpt: Path, sha: str, threads: int):
    """An ONNX Runtime CPU session of ``path``, checked to be ``role`` of checkpoint ``ckpt``
    (whose sha256 is ``sha``). Returns ``(session, metadata)``."""
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
            f"{ONNX_VERSION}; re-run visland export-onnx --checkpoint {ckpt}"
        )
    if meta.get("visland.checkpoint_sha256") != sha:
        raise OnnxModelError(
            f"{path}: exported from another checkpoint (sha256 "
            f"{str(meta.get('visland.checkpoint_sha256'))[:12]}…, the checkpoint now is "
            f"{sha[:12]}…): a stale export; re-run visland export-onnx --checkpoint {ckpt}"
        )
    return sess, meta


def _json_field(meta: dict[str, str], key: str, path: Path) -> Any:
    try:
        return json.loads(meta[key])
    except (KeyError, json.JSONDecodeError) as exc:
        raise OnnxModelError(
            f"{path}: metadata {key}: missing or not JSON ({exc}); re-run visland export-onnx"
        ) from None


def _zero_state(sess, n: int, path: Path) -> tuple[np.ndarray, ...]:
    """Zeros of the shapes of ``state_in_0..n-1`` at batch 1 (a symbolic axis is the batch)."""
    shapes = {i.name: i.shape for i in sess.get_inputs()}
    zero = []
    for k in range(n):
        shape = shapes.get(f"state_in_{k}")
        if shape is None:
            raise OnnxModelError(f"{path}: no input state_in_{k}; re-run visland export-onnx")
        dims = [d if isinstance(d, int) and d > 0 else 1 for d in shape]
        zero.append(np.zeros(dims, np.float32))
    return tuple(zero)


class OnnxPolicy(PolicyCore):
    """A learned policy whose networks run in ONNX Runtime (see the module doc); the rest is
    :class:`PolicyCore`, the code the torch policy flies."""

    def __init__(
        self,
        config: NetConfig,
        control_session,
        perception_session=None,
        zero_state: tuple[np.ndarray, ...] = (),
        metadata: dict[str, Any] | None = None,
    ) -> None:
        self.config = config
        if config.kind == "vision" and perception_session is None:
            raise CheckpointError("a vision policy needs its perception network")
        self._control = control_session
        self._perception = perception_session
        self._zero = zero_state
        self._outputs = ["command", *(f"state_out_{k}" for k in range(len(zero_state)))]
        self.metadata = dict(metadata or {})
        self._init_core()

    def perceive_batch(self, images_u8: np.ndarray) -> np.ndarray:
        """The CNN on a batch: (B, H, W) uint8 → (B, 3) float32."""
        assert self._perception is not None
        arr = np.ascontiguousarray(images_u8, dtype=np.uint8)
        (out,) = self._perception.run(["perception"], {"image": arr})
        return out

    def perceive(self, image: np.ndarray) -> np.ndarray:
        return self.perceive_batch(np.asarray(image)[None])[0].astype(float)

    def zero_state(self) -> tuple[np.ndarray, ...]:
        return tuple(z.copy() for z in self._zero)

    def control_step(
        self, features: np.ndarray, state: tuple[np.ndarray, ...]
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        feed = {"features": np.ascontiguousarray(features, np.float32).reshape(1, -1)}
        feed.update({f"state_in_{k}": s for k, s in enumerate(state)})
        res = self._control.run(self._outputs, feed)
        return res[0][0], tuple(res[1:])

    def control_sequence(self, features: np.ndarray) -> np.ndarray:
        """Commands (T, 4) for a sequence of features (T, F) from the zero state."""
        state, out = self.zero_state(), []
        for f in np.asarray(features, np.float32):
            cmd, state = self.control_step(f, state)
            out.append(cmd)
        return np.stack(out)


def load_onnx_policy(checkpoint: str | Path, threads: int = 1) -> OnnxPolicy:
    """The checkpoint's policy on ONNX Runtime (CPU, ``threads`` intra-op threads), read from
    the export beside it; the checkpoint file itself is only hashed (no torch needed).

    Raises:
        companion.policy_net.CheckpointError: the checkpoint file is missing.
        OnnxModelError: onnxruntime is not installed, or an ONNX file is missing, corrupt, of
            another export version or exported from another checkpoint (each names the file and
            the fix).
    """
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        raise OnnxModelError(f"runtime = 'onnx' needs onnxruntime: {INSTALL_HINT}") from None
    ckpt = Path(checkpoint)
    if not ckpt.is_file():
        raise CheckpointError(f"{ckpt}: no such checkpoint file")
    sha = sha256_file(ckpt)
    perception_path, control_path = onnx_paths(ckpt)
    control_sess, meta = _session(control_path, "control", ckpt, sha, threads)
    try:
        cfg = NetConfig.from_dict(dict(_json_field(meta, "visland.net_config", control_path)))
    except (TypeError, KeyError, ValueError) as exc:
        raise OnnxModelError(f"{control_path}: metadata visland.net_config: {exc}") from None
    expected = list(feature_names(cfg.hover_input))
    got = _json_field(meta, "visland.feature_names", control_path)
    if got != expected:
        raise OnnxModelError(
            f"{control_path}: feature_names {got!r} differ from this code's controller inputs "
            f"{expected!r}"
        )
    try:
        n_state = int(meta.get("visland.state_count", ""))
    except ValueError:
        raise OnnxModelError(
            f"{control_path}: metadata visland.state_count = "
            f"{meta.get('visland.state_count')!r}, expected an integer"
        ) from None
    zero = _zero_state(control_sess, n_state, control_path)
    perception_sess = None
    if cfg.kind == "vision":
        perception_sess, _ = _session(perception_path, "perception", ckpt, sha, threads)
    metadata = {
        **dict(_json_field(meta, "visland.checkpoint_metadata", control_path) or {}),
        "runtime": "onnx",
        "onnx": str(control_path),
    }
    return OnnxPolicy(cfg, control_sess, perception_sess, zero, metadata)
