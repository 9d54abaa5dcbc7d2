"""What a report reads from a run — ``metrics.json`` through the eval stage's own typed record
(``training.stage_records.Metrics``) — and the provenance lines naming the commits behind it."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from training.provenance import git_commit
from training.record import RecordError
from training.stage_records import Metrics

__all__ = ["CODE_DIRS", "ROWS", "Provenance", "ReportError", "code_commit", "load_metrics", "short"]

ROWS: dict[str, str] = {
    "expert": "MPC expert (privileged)",
    "bc": "LSTM behaviour cloning (privileged)",
    "dagger": "LSTM DAgger (privileged)",
    "vision": "CNN + LSTM (vision)",
}
"""The Table 3 rows of ``metrics.json`` ``rows``, in order, with their names in the report."""

CODE_DIRS = ("companion", "sitl_sim", "expert", "training", "tools", "configs")
"""The report's code: a change elsewhere (the docs it rewrites) does not make it dirty."""


class ReportError(ValueError):
    """The run cannot be reported: names the file and field, what was expected, and the fix."""


def load_metrics(run: str | Path) -> Metrics:
    """Read and check ``<run>/metrics.json``; :class:`ReportError` names any bad file/field."""
    path = Path(run) / "metrics.json"
    if not Path(run).is_dir():
        raise ReportError(f"{run}: no such run folder (make one with visland pipeline --out RUN)")
    if not path.is_file():
        raise ReportError(
            f"{path}: missing; run the pipeline's eval stage first "
            f"(visland train eval --run {run} --profile PROFILE)"
        )
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, ValueError) as exc:
        raise ReportError(
            f"{path}: not valid JSON ({exc}); regenerate it with the eval stage"
        ) from None
    try:
        return Metrics.from_dict(data, str(path))
    except (RecordError, ValueError) as exc:  # ValueError: a profile the pipeline refuses
        raise ReportError(f"{exc} (metrics.json as the pipeline's eval stage writes it)") from None


def code_commit() -> str:
    """HEAD of the checkout running the report, ``+dirty`` when its code differs from HEAD."""
    return git_commit(paths=CODE_DIRS)


def short(commit: str | None) -> str:
    """A commit for a footer: 10 hex digits, keeping ``+dirty`` and anything after a space."""
    if not commit:
        return "unknown"
    head, _, rest = commit.partition(" ")
    sha, plus, flag = head.partition("+")
    return sha[:10] + (f"+{flag}" if plus else "") + (f" {rest}" if rest else "")


@dataclass(frozen=True)
class Provenance:
    """The command and the commits behind a report, as figure footers and captions say them."""

    command: str
    code_commit: str
    run: Path
    run_commit: str

    def footer(self) -> str:
        return (
            f"{self.command}  ·  report code {short(self.code_commit)}  ·  "
            f"{self.run}/metrics.json from eval at {short(self.run_commit)}"
        )

    def caption(self) -> str:
        return (
            f"Made by `{self.command}` (code at `{short(self.code_commit)}`) from "
            f"`{self.run}/metrics.json` (eval stage at `{short(self.run_commit)}`)."
        )
