"""Which code made a result: the one git helper for stage records, flight logs and reports."""

from __future__ import annotations

import re
import subprocess
from collections.abc import Sequence
from pathlib import Path

__all__ = ["MODEL_NAME", "REPO", "SHIPPED_MODEL", "git_commit"]

REPO = Path(__file__).resolve().parent.parent
"""The checkout (or installed tree) holding this code: relative config, model and suite paths
resolve against it, and child processes start in it."""
SHIPPED_MODEL = REPO / "models" / "visland_vision.pt"
"""The shipped vision policy (README, ``models/MODEL_CARD.md``): the default model of ``visland
demo``, ``fly --companion-mode landing-target`` and the benchmarks; the one name for it."""
MODEL_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
"""What may follow ``visland_vision_`` in a shipped model's file name (a taught pad's name,
``visland ship --name``): a plain file-name word, no path."""


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(
        ["git", *args], capture_output=True, text=True, timeout=10, cwd=repo, check=True
    ).stdout.strip()


def git_commit(repo: str | Path | None = None, paths: Sequence[str] | None = None) -> str:
    """HEAD of ``repo`` (default: the checkout holding this code), ``<sha>+dirty`` when tracked
    files — under ``paths`` only, if given — differ from it (the code that ran is then not that
    commit); ``unknown`` outside a git checkout."""
    where = Path(repo) if repo is not None else REPO
    try:
        head = _git(where, "rev-parse", "HEAD")
        dirty = _git(where, "status", "--porcelain", "--untracked-files=no", "--", *(paths or ()))
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head}+dirty" if dirty else head
