"""Reading files the same way everywhere: a file's sha256, a TOML file with errors that name it.

Part of the deployable companion (standard library only), so the simulator, the expert and the
training pipeline use these too instead of keeping their own copies.
"""

from __future__ import annotations

import hashlib
import tomllib
from pathlib import Path
from typing import Any

__all__ = ["read_toml", "sha256_file"]

_BLOCK = 1 << 20


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks (checkpoints are tens of MB)."""
    h = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for block in iter(lambda: fh.read(_BLOCK), b""):
            h.update(block)
    return h.hexdigest()


def read_toml(path: str | Path, error: type[Exception] = ValueError) -> dict[str, Any]:
    """Parse a TOML file.

    Raises:
        error: (the caller's error type) the file is missing, unreadable or not valid TOML;
            the message starts with the path.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise error(f"{path}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc}") from None
