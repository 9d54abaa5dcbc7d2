"""``visland``: the one command-line entry point. It builds the top-level parser, asks each
command module to add its subcommands, runs the one asked for and turns its errors into exit
codes.

Each subcommand is a thin shell over a ``run(config)``-style function that the tests call
directly, registered by the module of its job:

- :mod:`tools.cli_sim`: ``demo``, ``readme``, ``sitl``, ``companion``, ``fly``, ``soak`` (the
  processes over MAVLink; ``readme`` writes the README's demo block from a demo run);
- :mod:`tools.cli_eval`: ``eval``, ``collect``, ``relabel``, ``pictures`` (flights in process);
- :mod:`tools.cli_log`: ``log info|plot|frame|replay|scene``;
- :mod:`tools.cli_bench`: ``bench sim|mpc|policy|companion|sitl|rollouts``;
- :mod:`tools.cli_train`: ``pipeline``, ``train``, ``ship``, ``report``;
- :mod:`tools.cli_pad`: ``pad info|print|check|acquire|error`` (make the landing pad, measure
  the CNN on it);
- :mod:`tools.export_onnx`: ``export-onnx``.

The flags and output several commands share are in :mod:`tools.cli_args`.

Exit codes: 0 done; 1 the work failed (a process, a backend, a failed episode where the command
says so); 2 an error a user can cause (bad config, bad file, bad value, a missing extra), which
ends with one line on stderr naming the problem, never a bare traceback; 130 interrupted. A
reader that closes the pipe early (``visland log info F | head``) ends the command quietly.

Every option's help says its default once (:class:`tools.cli_args.HelpFormatter`, set on every
subcommand here); ``visland --version`` names the package version and the checkout's commit.
"""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["main", "version_line"]


def version_line() -> str:
    """``visland <version>``, plus ``(git <commit>)`` when this code runs from a checkout."""
    from importlib.metadata import PackageNotFoundError, version

    from training.provenance import REPO, git_commit

    try:
        line = f"visland {version('visland')}"
    except PackageNotFoundError:
        line = "visland (not installed)"
    if (REPO / ".git").exists():
        line += f" (git {git_commit()})"
    return line


class _VersionAction(argparse.Action):
    """``--version``: the line of :func:`version_line`, worked out only when asked for."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(version_line())
        parser.exit()


def _with_formatter(parser: argparse.ArgumentParser, formatter: type) -> None:
    """``formatter`` for ``parser`` and every subcommand under it."""
    parser.formatter_class = formatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                _with_formatter(child, formatter)


def _parser() -> argparse.ArgumentParser:
    from tools.cli_args import HelpFormatter
    from tools.cli_bench import register_bench
    from tools.cli_eval import register_eval
    from tools.cli_log import register_log
    from tools.cli_pad import register_pad
    from tools.cli_sim import register_sim
    from tools.cli_train import register_training
    from tools.export_onnx import register_export

    p = argparse.ArgumentParser(
        prog="visland",
        description="Vision-based drone landing: simulator, companion, imitation learning.",
    )
    p.add_argument(
        "--version",
        action=_VersionAction,
        help="print the package version and git commit, then exit",
    )
    sub = p.add_subparsers(dest="command", required=True)
    for register in (
        register_sim,
        register_eval,
        register_log,
        register_bench,
        register_training,
        register_pad,
        register_export,
    ):
        register(sub)
    _with_formatter(p, HelpFormatter)
    return p


EXTRA_OF_MODULE = {
    "onnxruntime": "onnx",
    "torch": "torch",
    "cv2": "camera",
    "scipy": "sim",
    "pybullet": "sim",
    "gymnasium": "sim",
    "PIL": "sim",
    "cvxpy": "train",
    "osqp": "train",
    "clarabel": "train",
    "matplotlib": "train",
    "tqdm": "train",
    "tensorboard": "train",
    "tomli_w": "train",
    "onnx": "train",
    "ray": "ray",
    "foxglove": "live",
    "websockets": "dev",
    "mavsdk": "dev",
    "pytest": "dev",
}
"""Which ``pip install 'visland[EXTRA]'`` brings each optional module (pyproject.toml)."""


def missing_extra(exc: ImportError) -> str | None:
    """The line telling a user which extra a failed import needs; None for a module that no
    extra provides (a real bug, left to raise)."""
    top = (exc.name or "").split(".")[0]
    extra = EXTRA_OF_MODULE.get(top)
    if extra is None:
        return None
    return f"needs the '{extra}' extra (no module named {top!r}): pip install 'visland[{extra}]'"


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        code = _run(args)
        sys.stdout.flush()  # a pipe's buffer is written here, not at exit: a closed one raises
        return code
    except BrokenPipeError:
        # The reader left (``| head``): stop quietly. stdout points at /dev/null so that the
        # interpreter's own flush at exit does not raise again (Python docs, "Note on SIGPIPE").
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except ImportError as exc:
        line = missing_extra(exc)
        if line is None:
            raise
        print(f"visland {args.command}: {line}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    from companion.contract import ContractError
    from companion.flightlog import FlightLogError
    from sitl_sim.errors import SimError
    from training.exec.backend import BackendError

    try:
        return int(args.func(args))
    except (SimError, ContractError, FlightLogError, FileNotFoundError, ValueError) as exc:
        print(f"visland {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BackendError as exc:
        print(f"visland {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"visland {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
