"""Which backend a command gets: its ``--ray`` / ``--shared-dir`` flags and :func:`open_backend`.

A module of its own so that a command's parser can add the flags without loading a backend,
and so that the backends (``training.exec.backend``, ``training.exec.ray_backend``) import
nothing that chooses between them.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable
from pathlib import Path

from training.exec.backend import Backend, LocalBackend

__all__ = ["add_backend_arguments", "backend_from_args", "check_ray_address", "open_backend"]

_RAY_ADDRESS = re.compile(r"^(auto|local|ray://[^\s:/]+:\d+|[^\s:/]+:\d+)$")


def check_ray_address(address: str) -> str:
    """``auto`` | ``local`` | ``ray://HOST:PORT`` | ``HOST:PORT``, or a ValueError that says so."""
    if not _RAY_ADDRESS.match(address):
        raise ValueError(
            f"--ray {address!r}: expected auto (the cluster this node belongs to), local (a Ray "
            "instance in this process), ray://HOST:PORT (Ray Client) or HOST:PORT (the head "
            "node's GCS address, as printed by `ray start --head`)"
        )
    return address


def open_backend(
    ray: str | None = None,
    workers: int = 1,
    shared_dir: str | Path | None = None,
    say: Callable[[str], None] | None = None,
) -> Backend:
    """The local backend with ``workers`` (``ray`` None), or a Ray backend connected to
    ``ray`` (see :func:`check_ray_address`). ``shared_dir``: Ray only — a folder every node
    sees at the same path, through which logs travel instead of as objects."""
    if ray is None:
        if shared_dir is not None:
            raise ValueError("--shared-dir is for --ray runs (the local backend writes in place)")
        return LocalBackend(workers)
    from training.exec.ray_backend import RayBackend  # Ray only when asked for

    return RayBackend(check_ray_address(ray), shared_dir=shared_dir, say=say)


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    """``--ray ADDRESS`` and ``--shared-dir DIR`` (a command's ``--workers`` / ``--instances``
    stays the local backend's parallelism)."""
    parser.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help="fly the episodes on a Ray cluster (pip install 'visland[ray]'): auto, local (a "
        "Ray instance started in this process), ray://HOST:PORT or HOST:PORT; every node must "
        "run the same visland commit; the cluster's CPUs then set the parallelism (--workers / "
        "--instances are for this host)",
    )
    parser.add_argument(
        "--shared-dir",
        default=None,
        metavar="DIR",
        help="with --ray: a folder mounted at the same path on every node; flight logs travel "
        "through it instead of as Ray objects",
    )


def backend_from_args(args: argparse.Namespace, workers: int = 1) -> Backend:
    """The backend a command's ``--ray`` / ``--shared-dir`` (and ``workers``) ask for."""
    return open_backend(
        getattr(args, "ray", None),
        workers,
        getattr(args, "shared_dir", None),
        say=lambda msg: print(msg, file=sys.stderr, flush=True),
    )
