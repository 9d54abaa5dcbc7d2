"""``visland export-onnx``: a checkpoint's networks as ONNX graphs for ``runtime = "onnx"``.

A thin shell over :func:`companion.onnx_export.export_onnx`: writes
``<stem>.perception.onnx`` and ``<stem>.control.onnx`` beside the checkpoint, checks that ONNX
Runtime reproduces torch on random inputs, prints what it wrote and the differences. Needs the
``onnx`` extra (``pip install 'visland[onnx]'``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tools.cli_args import json_command
from training.provenance import REPO, SHIPPED_MODEL

__all__ = ["main", "register_export"]


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    from companion.onnx_export import export_onnx

    res = export_onnx(args.checkpoint, check_samples=args.check_samples)
    if args.json:
        print(json.dumps(res.to_dict(), indent=2))
        return 0
    print(f"exported {res.checkpoint} (sha256 {res.checkpoint_sha256[:12]}…, opset {res.opset}):")
    if res.perception:
        print(
            f"  {res.perception}  CNN, max |onnxruntime - torch| / max(1, |torch|) = "
            f"{res.perception_max_rel_diff:.2g} over {res.check_samples} random images"
        )
    print(
        f"  {res.control}  LSTM step, max |onnxruntime - torch| = "
        f"{res.control_max_abs_diff:.2g} over a {res.check_samples}-step rollout"
    )
    print(f"fly it with: visland companion --policy {res.checkpoint} --runtime onnx ...")
    return 0


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=SHIPPED_MODEL,
        help="policy checkpoint; the .onnx files go beside it (default: the shipped model, "
        f"{SHIPPED_MODEL.relative_to(REPO)})",
    )
    p.add_argument(
        "--check-samples",
        type=int,
        default=64,
        help="random images / rollout steps on which ONNX Runtime must match torch",
    )
    json_command(p, _cmd_export_onnx)


def register_export(sub: argparse._SubParsersAction) -> None:
    """Add ``export-onnx`` to the ``visland`` subcommands."""
    _add_arguments(
        sub.add_parser(
            "export-onnx",
            help="a checkpoint's CNN and LSTM step as ONNX graphs (companion --runtime onnx)",
        )
    )


def main(argv: list[str] | None = None) -> int:
    """``python -m tools.export_onnx`` (the same as ``visland export-onnx``)."""
    p = argparse.ArgumentParser(prog="python -m tools.export_onnx", description=__doc__)
    _add_arguments(p)
    args = p.parse_args(argv)
    try:
        return _cmd_export_onnx(args)
    except ValueError as exc:  # CheckpointError, OnnxModelError: one clear line
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
