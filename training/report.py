"""``visland report``: ``docs/results.md`` and its figures, generated from a run's ``metrics.json``.

Every number in the report is read from the run (``<run>/metrics.json``, written by the
pipeline's eval stage; ``<run>/scalars.jsonl`` for the loss curves) or computed from it here; the
only numbers typed in this module are the paper's own (:data:`PAPER_TABLE3`,
:data:`PAPER_RUNTIME_S`, cited by section) and the project's targets (:data:`TARGETS`). The
trajectory figures (the kind of the paper's Figures 3-11) come from flying one evaluation episode
in process with each of the run's four policies — the same seed and episode index the eval stage
flew, so each flight is checked against its ``per_episode`` row (lockstep flights are
deterministic). Each figure carries the command and the commits that made it in a footer, and
each caption in the markdown says the same.

The landing scatter needs ``per_episode[*].touchdown_ne_m`` (recorded by
``training.rollout.fly_episode`` since it was added); for a run evaluated before that, the report
says the scatter is unavailable and which command regenerates the eval stage — it never guesses
positions.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "PAPER_RUNTIME_S",
    "PAPER_TABLE3",
    "ROWS",
    "TARGETS",
    "ReportConfig",
    "ReportError",
    "ReportResult",
    "Target",
    "load_metrics",
    "write_report",
]

ROWS: dict[str, str] = {
    "expert": "MPC expert (privileged)",
    "bc": "LSTM behaviour cloning (privileged)",
    "dagger": "LSTM DAgger (privileged)",
    "vision": "CNN + LSTM (vision)",
}
"""The Table 3 rows of ``metrics.json`` ``rows``, in order, with their names in the report."""

PAPER_TABLE3: dict[str, dict[str, float]] = {
    "bc": {"min": 1.56, "max": 10.47, "mean": 5.74, "std": 2.14},
    "dagger": {"min": 0.56, "max": 0.91, "mean": 0.70, "std": 0.09},
    "vision": {"min": 0.54, "max": 1.27, "mean": 0.84, "std": 0.21},
}
"""Paper section 5.4, Table 3 "Landing Performance Metrics": landing error in m. The paper has
no expert row and reports neither touchdown speed nor success rate there (section 5.5 says only,
from its Figure 6, that the vision policy's terminal velocity is "approximately 5 m/s")."""

PAPER_VISION_TERMINAL_SPEED_M_S = 5.0
"""Paper section 5.5 (qualitative, read off its Figure 6): the vision policy's terminal velocity."""

PAPER_RUNTIME_S: dict[str, float] = {
    "mpc_mean": 0.125,
    "mpc_std": 0.025,
    "policy_mean": 0.0132,
    "policy_std": 0.0014,
}
"""Paper section 6 "Runtime Efficiency": seconds per control input, MPC expert vs CNN+LSTM."""


@dataclass(frozen=True)
class Target:
    """One acceptance target: ``rows[row][metric][stat] <op> limit`` (``stat`` None: a scalar)."""

    row: str
    metric: str
    stat: str | None
    op: str
    limit: float
    unit: str

    def describe(self) -> str:
        what = f"{self.metric}.{self.stat}" if self.stat else self.metric
        limit = f"{100 * self.limit:g} %" if self.unit == "%" else f"{self.limit:g} {self.unit}"
        return f"{ROWS[self.row]}: {what} {'≤' if self.op == '<=' else '≥'} {limit}"

    def value(self, rows: dict[str, Any]) -> float | None:
        v = rows[self.row][self.metric]
        return v[self.stat] if self.stat else v

    def met(self, rows: dict[str, Any]) -> bool:
        v = self.value(rows)
        if v is None or not math.isfinite(v):
            return False
        return v <= self.limit if self.op == "<=" else v >= self.limit


TARGETS: tuple[Target, ...] = (
    Target("dagger", "landing_error_m", "mean", "<=", 0.30, "m"),
    Target("vision", "landing_error_m", "mean", "<=", 0.50, "m"),
    Target("vision", "landing_error_m", "max", "<=", 1.2, "m"),
    Target("vision", "touchdown_speed_m_s", "mean", "<=", 1.0, "m/s"),
    Target("vision", "success_rate", None, ">=", 0.95, "%"),
)
"""The project's targets for the Table 3 rows (the issue's acceptance figures)."""

_COLORS = {"expert": "k", "bc": "tab:orange", "dagger": "tab:blue", "vision": "tab:green"}
_STATS = ("min", "max", "mean", "std")
_SCATTER_VIEW_M = 3.0  # half-width of the scatter's view: the 4 m pad plus a margin
_CODE_DIRS = ("companion", "sitl_sim", "expert", "training", "tools", "configs")
_FIGURE_PATTERNS = (
    "trajectory_*.png",
    "landing_scatter.png",
    "landing_error_hist.png",
    "training_loss.png",
)


class ReportError(ValueError):
    """The run cannot be reported: names the file and field, what was expected, and the fix."""


@dataclass(frozen=True)
class ReportConfig:
    """Options of ``visland report``."""

    run: Path
    """Run folder with ``metrics.json`` (``visland pipeline --out RUN``)."""
    out: Path = Path("docs/results.md")
    """The markdown file to write."""
    figures_dir: Path | None = None
    """Where the PNGs go (default: ``figures/`` beside ``out``)."""
    trajectories: bool = True
    """Fly the trajectory episodes in process (four policies; ``False`` skips those figures)."""
    trajectory_episodes: tuple[int, ...] | None = None
    """Eval episode indices to fly (default: episode 0 and the vision row's worst episode)."""

    def figures(self) -> Path:
        return Path(self.figures_dir) if self.figures_dir else Path(self.out).parent / "figures"

    def command(self) -> str:
        """The ``visland report`` command line that reproduces this report."""
        parts = ["visland report", f"--run {self.run}"]
        if Path(self.out) != Path("docs/results.md"):
            parts.append(f"--out {self.out}")
        if self.figures_dir is not None and self.figures() != Path(self.out).parent / "figures":
            parts.append(f"--figures-dir {self.figures_dir}")
        if not self.trajectories:
            parts.append("--no-trajectories")
        return " ".join(parts)


@dataclass(frozen=True)
class ReportResult:
    """What :func:`write_report` wrote and how the run stands against :data:`TARGETS`."""

    out: Path
    figures: tuple[Path, ...]
    targets_met: tuple[bool, ...]
    standing: str
    notes: tuple[str, ...] = field(default_factory=tuple)


# ------------------------------------------------------------------------------ reading the run


def _where(path: Path, keys: Sequence[str | int]) -> str:
    name = "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in keys).lstrip(".")
    return f"{path}: field {name}"


def _need(
    obj: Any, path: Path, keys: Sequence[str | int], kinds: tuple[type, ...], what: str
) -> Any:
    """``obj[keys[0]][keys[1]]...``, which must be one of ``kinds`` (bool only if listed)."""
    cur = obj
    for i, k in enumerate(keys):
        if isinstance(k, str):
            ok = isinstance(cur, dict) and k in cur
        else:
            ok = isinstance(cur, list) and 0 <= k < len(cur)
        if not ok:
            raise ReportError(
                f"{_where(path, keys[: i + 1])} is missing; expected {what} "
                "(metrics.json as the pipeline's eval stage writes it)"
            )
        cur = cur[k]
    if not isinstance(cur, kinds) or (isinstance(cur, bool) and bool not in kinds):
        raise ReportError(f"{_where(path, keys)}: expected {what}, got {cur!r:.60}")
    return cur


def _number_or_null(obj: Any, path: Path, keys: Sequence[str | int]) -> None:
    _need(obj, path, keys, (int, float, type(None)), "a number or null")


def load_metrics(run: str | Path) -> dict[str, Any]:
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
        metrics = json.loads(path.read_text())
    except (UnicodeDecodeError, ValueError) as exc:
        raise ReportError(
            f"{path}: not valid JSON ({exc}); regenerate it with the eval stage"
        ) from None
    if not isinstance(metrics, dict):
        raise ReportError(f"{path}: expected a JSON object, got {type(metrics).__name__}")
    _need(metrics, path, ["rows"], (dict,), "an object with rows " + ", ".join(ROWS))
    _need(metrics, path, ["eval_seed"], (int,), "the evaluation seed (integer)")
    _need(metrics, path, ["episodes"], (int,), "the episode count per row (integer)")
    _need(metrics, path, ["profile"], (dict,), "the pipeline profile (object)")
    for row in ROWS:
        _need(metrics, path, ["rows", row], (dict,), f"the {ROWS[row]} row (object)")
        for metric in ("landing_error_m", "touchdown_speed_m_s"):
            for stat in _STATS:
                _number_or_null(metrics, path, ["rows", row, metric, stat])
        _number_or_null(metrics, path, ["rows", row, "success_rate"])
        eps = _need(metrics, path, ["rows", row, "per_episode"], (list,), "a list of episodes")
        for i, ep in enumerate(eps):
            at = ["rows", row, "per_episode", i]
            _need(metrics, path, at, (dict,), "an episode record")
            _need(metrics, path, [*at, "episode"], (int,), "the episode index (integer)")
            _number_or_null(metrics, path, [*at, "landing_error_m"])
            _need(metrics, path, [*at, "success"], (bool,), "true or false")
            ne = ep.get("touchdown_ne_m")
            if ne is not None and not (
                isinstance(ne, list)
                and len(ne) == 2
                and all(isinstance(v, int | float) and not isinstance(v, bool) for v in ne)
            ):
                raise ReportError(
                    f"{_where(path, [*at, 'touchdown_ne_m'])}: expected [north, east] in m, "
                    f"got {ne!r:.60}"
                )
    return metrics


# ------------------------------------------------------------------------------ provenance


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args],
            capture_output=True,
            text=True,
            timeout=10,
            cwd=Path(__file__).resolve().parent,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def _code_commit() -> str:
    """HEAD of the checkout running the report, flagged when its code differs from HEAD."""
    head = _git("rev-parse", "HEAD") or "unknown"
    changed = _git("status", "--porcelain", "--untracked-files=no", "--", *_CODE_DIRS)
    return f"{head} (+ uncommitted changes)" if changed else head


def _short(commit: str | None) -> str:
    if not commit:
        return "unknown"
    head, _, rest = commit.partition(" ")
    sha, plus, flag = head.partition("+")  # "<sha>+dirty" from training.rollout.git_commit
    return sha[:10] + (f"+{flag}" if plus else "") + (f" {rest}" if rest else "")


@dataclass(frozen=True)
class _Provenance:
    command: str
    code_commit: str
    run: Path
    run_commit: str

    def footer(self) -> str:
        return (
            f"{self.command}  ·  report code {_short(self.code_commit)}  ·  "
            f"{self.run}/metrics.json from eval at {_short(self.run_commit)}"
        )

    def caption(self) -> str:
        return (
            f"Made by `{self.command}` (code at `{_short(self.code_commit)}`) from "
            f"`{self.run}/metrics.json` (eval stage at `{_short(self.run_commit)}`)."
        )


# ------------------------------------------------------------------------------ formatting


def _f(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if v != 0 and abs(v) < 10 ** (-digits):
        return f"{v:.1e}"
    return f"{v:.{digits}f}"


def _pct(v: Any) -> str:
    return "n/a" if v is None else f"{100 * v:.1f} %"


# ------------------------------------------------------------------------------ trajectories


@dataclass
class _Trace:
    """One flown episode: per control step, ground truth and the command the policy gave."""

    name: str
    time_s: list[float] = field(default_factory=list)
    pos_ned_m: list[np.ndarray] = field(default_factory=list)
    vel_ned_m_s: list[np.ndarray] = field(default_factory=list)
    euler_rad: list[np.ndarray] = field(default_factory=list)
    thrust_norm: list[float] = field(default_factory=list)
    rate_frd_rad_s: list[np.ndarray] = field(default_factory=list)
    landing_error_m: float = math.nan
    landed: bool = False
    eval_error_m: float | None = None


class _Recording:
    """Wraps a policy; records ground truth and command at every control step it answers."""

    def __init__(self, policy: Any, trace: _Trace) -> None:
        from sitl_sim.dynamics import euler_from_quat

        self._policy = policy
        self._trace = trace
        self._euler = euler_from_quat
        self.privileged = bool(getattr(policy, "privileged", False))

    def initial_state(self) -> Any:
        return self._policy.initial_state()

    def act(self, observation: Any, groundtruth: Any, state: Any) -> tuple[Any, Any]:
        command, state = self._policy.act(observation, groundtruth, state)
        t = self._trace
        t.time_s.append(float(groundtruth.time_s))
        t.pos_ned_m.append(np.array(groundtruth.pos_ned_m, dtype=float))
        t.vel_ned_m_s.append(np.array(groundtruth.vel_ned_m_s, dtype=float))
        t.euler_rad.append(np.asarray(self._euler(np.asarray(groundtruth.quat_wxyz)), float))
        t.thrust_norm.append(float(command.thrust_norm))
        t.rate_frd_rad_s.append(np.array(command.rate_frd_rad_s, dtype=float))
        return command, state


def _scenario(metrics: dict[str, Any], path: Path) -> str | None:
    s = metrics["rows"]["expert"].get("scenario")
    if s is None or (s == "configs/scenario.toml" and not Path(s).is_file()):
        return None  # the repository's default scenario, wherever the report runs from
    if not isinstance(s, str) or not Path(s).is_file():
        raise ReportError(
            f"{_where(path, ['rows', 'expert', 'scenario'])}: scenario file {s!r} not found "
            "(run the report from the folder the pipeline ran in, or use --no-trajectories)"
        )
    return s


def _policy_source(metrics: dict[str, Any], run: Path, row: str) -> str:
    """The policy the eval stage flew for ``row``: ``expert`` or its checkpoint file."""
    name = metrics["rows"][row].get("policy", "expert" if row == "expert" else None)
    if name is not None and not isinstance(name, str):
        raise ReportError(
            f"{_where(run / 'metrics.json', ['rows', row, 'policy'])}: expected 'expert' or a "
            f"checkpoint path, got {name!r:.60}"
        )
    if name == "expert":
        return name
    candidates = [Path(name)] if name else []
    candidates.append(run / "checkpoints" / (Path(name).name if name else f"{row}.pt"))
    for c in candidates:
        if c.is_file():
            return str(c)
    raise ReportError(
        f"{_where(run / 'metrics.json', ['rows', row, 'policy'])}: checkpoint {name!r} not "
        f"found (nor {candidates[-1]}); restore the run's checkpoints or use --no-trajectories"
    )


def _fly_traces(
    metrics: dict[str, Any], run: Path, episode: int, scenario: str | None
) -> dict[str, _Trace]:
    from companion.policy_net import load_policy
    from sitl_sim.env import LandingEnv
    from training.rollout import fly_episode, make_policy

    seed = int(metrics["eval_seed"])
    traces = {}
    for row in ROWS:
        source = _policy_source(metrics, run, row)
        trace = _Trace(row)
        # As the eval stage: the camera is rendered only for policies that look at it.
        camera = source != "expert" and not load_policy(source).privileged
        env = LandingEnv(scenario=scenario, render_camera=camera)
        try:
            policy = make_policy(source, env)
            out = fly_episode(env, _Recording(policy, trace), seed, episode)
        finally:
            env.close()
        trace.landing_error_m = out.result.landing_error_m
        trace.landed = out.result.landed
        match = [
            e
            for e in metrics["rows"][row]["per_episode"]
            if e["episode"] == episode and e.get("seed", seed) == seed
        ]
        if match:
            trace.eval_error_m = match[0]["landing_error_m"]
        traces[row] = trace
    return traces


def _default_episodes(metrics: dict[str, Any]) -> tuple[int, ...]:
    eps = [e for e in metrics["rows"]["vision"]["per_episode"] if e["landing_error_m"] is not None]
    first = min((e["episode"] for e in metrics["rows"]["vision"]["per_episode"]), default=0)
    if not eps:
        return (first,)
    worst = max(eps, key=lambda e: e["landing_error_m"])["episode"]
    return (first,) if worst == first else (first, worst)


# ------------------------------------------------------------------------------ figures


def _plt():
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path, prov: _Provenance) -> Path:
    fig.text(0.005, 0.003, prov.footer(), fontsize=6, color="0.35", ha="left", va="bottom")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80, pil_kwargs={"optimize": True})
    _plt().close(fig)
    return path


def _plot_states(traces: dict[str, _Trace], title: str, path: Path, prov: _Provenance) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(3, 3, figsize=(11, 8), sharex=True)
    panels = [
        ("north (m)", lambda t: np.array(t.pos_ned_m)[:, 0]),
        ("east (m)", lambda t: np.array(t.pos_ned_m)[:, 1]),
        ("altitude (m)", lambda t: -np.array(t.pos_ned_m)[:, 2]),
        ("v north (m/s)", lambda t: np.array(t.vel_ned_m_s)[:, 0]),
        ("v east (m/s)", lambda t: np.array(t.vel_ned_m_s)[:, 1]),
        ("v down (m/s)", lambda t: np.array(t.vel_ned_m_s)[:, 2]),
        ("roll (deg)", lambda t: np.degrees(np.array(t.euler_rad)[:, 0])),
        ("pitch (deg)", lambda t: np.degrees(np.array(t.euler_rad)[:, 1])),
        ("yaw (deg, unwrapped)", lambda t: np.degrees(np.unwrap(np.array(t.euler_rad)[:, 2]))),
    ]
    for ax, (label, get) in zip(axes.flat, panels, strict=True):
        for row, tr in traces.items():
            if tr.time_s:
                ax.plot(tr.time_s, get(tr), color=_COLORS[row], linewidth=1.0, label=ROWS[row])
        ax.set_ylabel(label, fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.02, 1, 1))
    return _save(fig, path, prov)


def _plot_inputs(traces: dict[str, _Trace], title: str, path: Path, prov: _Provenance) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(12, 6.5), sharex=True)
    panels = [
        ("thrust_norm", lambda t: np.array(t.thrust_norm)),
        ("p, roll rate (rad/s)", lambda t: np.array(t.rate_frd_rad_s)[:, 0]),
        ("q, pitch rate (rad/s)", lambda t: np.array(t.rate_frd_rad_s)[:, 1]),
        ("r, yaw rate (rad/s)", lambda t: np.array(t.rate_frd_rad_s)[:, 2]),
    ]
    for ax, (label, get) in zip(axes.flat, panels, strict=True):
        for row, tr in traces.items():
            if tr.time_s:
                ax.step(
                    tr.time_s,
                    get(tr),
                    where="post",
                    color=_COLORS[row],
                    linewidth=0.9,
                    label=ROWS[row],
                )
        ax.set_ylabel(label, fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.02, 1, 1))
    return _save(fig, path, prov)


def _draw_pad(ax: Any) -> None:
    from matplotlib.patches import Circle, Rectangle

    from sitl_sim.scene import PadGeometry

    pad = PadGeometry()
    s, a, w = pad.side_m / 2, pad.cross_length_m / 2, pad.cross_width_m / 2
    ax.add_patch(Rectangle((-s, -s), 2 * s, 2 * s, color=pad.green_rgb, alpha=0.35, zorder=0))
    ax.add_patch(Rectangle((-a, -w), 2 * a, 2 * w, color=pad.red_rgb, alpha=0.35, zorder=0))
    ax.add_patch(Rectangle((-w, -a), 2 * w, 2 * a, color=pad.red_rgb, alpha=0.35, zorder=0))
    from sitl_sim.metrics import SUCCESS_MAX_ERROR_M

    ax.add_patch(Circle((0, 0), SUCCESS_MAX_ERROR_M, fill=False, linestyle="--", color="0.3"))


def _touchdowns(metrics: dict[str, Any]) -> dict[str, tuple[np.ndarray, np.ndarray, int]]:
    """Per row: (N x 2 north/east, success flags, episodes lacking a position)."""
    out = {}
    for row in ROWS:
        eps = metrics["rows"][row]["per_episode"]
        have = [e for e in eps if e.get("touchdown_ne_m") is not None]
        ne = np.array([e["touchdown_ne_m"] for e in have], dtype=float).reshape(-1, 2)
        ok = np.array([bool(e["success"]) for e in have], dtype=bool)
        out[row] = (ne, ok, len(eps) - len(have))
    return out


def _plot_scatter(metrics: dict[str, Any], path: Path, prov: _Provenance) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(10, 10))
    view = _SCATTER_VIEW_M
    for ax, (row, (ne, ok, lacking)) in zip(axes.flat, _touchdowns(metrics).items(), strict=True):
        _draw_pad(ax)
        dist = np.hypot(ne[:, 0], ne[:, 1]) if len(ne) else np.zeros(0)
        inside = np.all(np.abs(ne) <= view, axis=1) if len(ne) else np.zeros(0, bool)
        for mask, color, label in ((ok, "tab:green", "success"), (~ok, "tab:red", "failure")):
            sel = mask & inside
            ax.plot(
                ne[sel, 1],
                ne[sel, 0],
                ".",
                color=color,
                markersize=5,
                alpha=0.7,
                label=f"{label} ({int(mask.sum())})",
            )
            far = mask & ~inside
            if far.any():  # outside the view: drawn on its border, in the direction it lies
                edge = ne[far] * (view / np.max(np.abs(ne[far]), axis=1))[:, None]
                ax.plot(edge[:, 1], edge[:, 0], "^", color=color, markersize=6, alpha=0.8)
        n_far = int((~inside).sum())
        far_txt = (
            f"\n{n_far} outside ±{view:g} m (▲ on the border), farthest {dist.max():.1f} m"
            if n_far
            else ""
        )
        lack_txt = f"\n{lacking} episodes without a recorded position" if lacking else ""
        ax.set_title(f"{ROWS[row]}: {len(ne)} episodes{far_txt}{lack_txt}", fontsize=9)
        ax.set_xlim(-view * 1.05, view * 1.05)
        ax.set_ylim(-view * 1.05, view * 1.05)
        ax.set_aspect("equal")
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(
        f"Touchdown positions around the pad, {metrics['episodes']} eval episodes per policy "
        f"(seed {metrics['eval_seed']}); dashed circle = 1 m success radius",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.02, 1, 1))
    return _save(fig, path, prov)


def _plot_hist(metrics: dict[str, Any], path: Path, prov: _Provenance) -> Path:
    plt = _plt()
    errs = {
        row: np.array(
            [
                e["landing_error_m"]
                for e in metrics["rows"][row]["per_episode"]
                if e["landing_error_m"] is not None
            ],
            dtype=float,
        )
        for row in ROWS
    }
    pooled = np.concatenate([e[e > 0] for e in errs.values()] + [np.array([1e-3, 1.0])])
    lo = 10 ** math.floor(math.log10(pooled.min()))
    hi = 10 ** math.ceil(math.log10(pooled.max()))
    bins = np.logspace(math.log10(lo), math.log10(hi), 60)
    fig, ax = plt.subplots(figsize=(10, 5))
    for row, e in errs.items():
        ax.hist(
            np.clip(e, lo, hi),
            bins=bins,
            histtype="step",
            linewidth=1.6,
            color=_COLORS[row],
            label=f"{ROWS[row]} (n={len(e)})",
        )
        if row in PAPER_TABLE3:
            ax.axvline(PAPER_TABLE3[row]["mean"], color=_COLORS[row], linestyle=":", linewidth=1.2)
    from sitl_sim.metrics import SUCCESS_MAX_ERROR_M

    ax.axvline(
        SUCCESS_MAX_ERROR_M,
        color="tab:red",
        linestyle="--",
        linewidth=1.2,
        label=f"success limit {SUCCESS_MAX_ERROR_M:g} m",
    )
    ax.plot([], [], color="0.4", linestyle=":", label="paper Table 3 mean (row colour)")
    ax.set_xscale("log")
    ax.set_xlabel("landing error (m, log scale)")
    ax.set_ylabel("episodes")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(
        f"Landing error per eval episode (seed {metrics['eval_seed']}); errors below "
        f"{lo:g} m are counted in the first bin",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    return _save(fig, path, prov)


def _loss_series(run: Path) -> dict[str, list[tuple[int, float]]]:
    """Controller loss curves from ``scalars.jsonl``; a name logged again (a rerun) keeps its
    last run only (its steps restart at 0)."""
    path = run / "scalars.jsonl"
    series: dict[str, list[tuple[int, float]]] = {}
    if not path.is_file():
        return series
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            rec = json.loads(line)
            name, step, value = rec["name"], int(rec["step"]), float(rec["value"])
        except (ValueError, KeyError, TypeError) as exc:
            raise ReportError(f"{path}: line {n} is not a scalar record ({exc})") from None
        if not (name.startswith("controller/") and name.endswith("/loss")):
            continue
        stage = name.split("/")[1]
        cur = series.setdefault(stage, [])
        if cur and step <= cur[-1][0]:
            cur.clear()
        cur.append((step, value))
    return series


def _plot_loss(
    series: dict[str, list[tuple[int, float]]], path: Path, prov: _Provenance
) -> Path | None:
    groups = [
        ("privileged LSTM: BC, then DAgger rounds", ["bc"], "dagger_r"),
        ("vision: LSTM on CNN features, then vision DAgger rounds", ["vision_bc"], "vision_r"),
    ]
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    drew = False
    for ax, (title, first, prefix) in zip(axes, groups, strict=True):
        rounds = sorted(
            (k for k in series if k.startswith(prefix) and k[len(prefix) :].isdigit()),
            key=lambda k: int(k[len(prefix) :]),
        )
        offset = 0
        for stage in [k for k in first if k in series] + rounds:
            steps, values = zip(*series[stage], strict=True)
            x = np.array(steps) + offset
            ax.plot(x, values, linewidth=1.0, label=stage)
            if offset:
                ax.axvline(offset, color="0.4", linestyle=":", linewidth=1.0)
                ax.annotate(
                    "aggregate",
                    (offset, max(values)),
                    fontsize=7,
                    rotation=90,
                    va="top",
                    ha="right",
                    color="0.3",
                )
            offset = int(x[-1]) + 1
            drew = True
        ax.set_yscale("log")
        ax.set_xlabel("optimiser step (stages concatenated)")
        ax.set_ylabel("training loss")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3, which="both")
        if ax.lines:
            ax.legend(fontsize=7)
    if not drew:
        plt.close(fig)
        return None
    fig.suptitle("Controller training loss over DAgger rounds (paper Figure 5)", fontsize=10)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    return _save(fig, path, prov)


# ------------------------------------------------------------------------------ markdown


def _seed_line(metrics: dict[str, Any]) -> str:
    p = metrics["profile"]
    ev, n = int(metrics["eval_seed"]), int(metrics["episodes"])
    used: dict[str, list[int]] = {}
    if isinstance(p.get("collect_seed"), int):
        used["expert collection"] = [p["collect_seed"]]
    for key, rounds in (("dagger_seed", "dagger_rounds"), ("vision_seed", "vision_rounds")):
        if isinstance(p.get(key), int):
            used[key.split("_")[0] + " rollouts"] = [
                p[key] + k for k in range(max(1, int(p.get(rounds) or 1)))
            ]
    if isinstance(p.get("validation_seed"), int):
        used["validation"] = [p["validation_seed"]]
    if not used:
        return (
            f"Evaluation: {n} episodes per row, seed {ev} (episodes 0–{n - 1}); the profile "
            "records no training seeds, so disjointness cannot be checked."
        )
    clash = sorted({k for k, seeds in used.items() if ev in seeds})
    listing = "; ".join(f"{k} {', '.join(map(str, v))}" for k, v in used.items())
    verdict = (
        "**not disjoint** — the evaluation seed was also used for " + ", ".join(clash)
        if clash
        else "disjoint from every seed used in training and model selection"
    )
    return (
        f"Evaluation: {n} episodes per row, seed {ev} (episode indices 0–{n - 1}); seeds used "
        f"before it ({listing}) — the evaluation seed is {verdict}. An episode's initial state "
        "is a function of (seed, index) only (DESIGN.md, Seeds)."
    )


def _table3(metrics: dict[str, Any]) -> str:
    rows = metrics["rows"]
    lines = [
        "| policy | source | min error (m) | max error (m) | mean error (m) | std error (m) "
        "| touchdown speed mean / max (m/s) | success | timeouts |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, label in ROWS.items():
        r = rows[key]
        e, v = r["landing_error_m"], r["touchdown_speed_m_s"]
        lines.append(
            f"| {label} | **ours** | {_f(e['min'])} | {_f(e['max'])} | {_f(e['mean'])} | "
            f"{_f(e['std'])} | {_f(v['mean'])} / {_f(v['max'])} | {_pct(r['success_rate'])} | "
            f"{r.get('timeouts', 'n/a')} |"
        )
        paper = PAPER_TABLE3.get(key)
        if paper is None:
            lines.append(f"| {label} | paper | — | — | — | — | — | — | — |")
        else:
            td = (
                f"≈ {PAPER_VISION_TERMINAL_SPEED_M_S:g} (§5.5, qualitative)"
                if key == "vision"
                else "not reported"
            )
            lines.append(
                f"| {label} | paper | {paper['min']:.2f} | {paper['max']:.2f} | "
                f"{paper['mean']:.2f} | {paper['std']:.2f} | {td} | not reported | — |"
            )
    return "\n".join(lines)


def _ms(d: dict[str, Any], key: str) -> float | None:
    v = d.get(key)
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def _runtime(metrics: dict[str, Any], path: Path) -> str:
    timing = metrics.get("timing")
    if not isinstance(timing, dict):
        return (
            f"`{path}` has no `timing` object (the eval stage writes it with "
            "`training.pipeline.inference_timing`); no runtime comparison for this run."
        )
    pol = timing.get("policy") if isinstance(timing.get("policy"), dict) else {}
    mpc = timing.get("mpc") if isinstance(timing.get("mpc"), dict) else {}
    shipped = pol.get("shipped") if isinstance(pol.get("shipped"), dict) else {}
    style = pol.get("paper_style") if isinstance(pol.get("paper_style"), dict) else {}
    mpc_ms, pol_ms = _ms(mpc, "median_ms"), _ms(shipped, "median_ms")
    base_ms, style_ms = _ms(mpc, "baseline_median_ms"), _ms(style, "median_ms")
    p = PAPER_RUNTIME_S
    paper_ratio = p["mpc_mean"] / p["policy_mean"]

    def ratio(a: float | None, b: float | None) -> str:
        return f"{a / b:.2f}×" if a is not None and b else "n/a"

    def params(d: dict[str, Any]) -> str:
        n = d.get("parameters")
        return f", {n:,} parameters" if isinstance(n, int) else ""

    lines = [
        "| per control step | ours, median (tail) | paper (mean ± std) |",
        "|---|---:|---:|",
        f"| MPC expert (`expert.mpc`, OSQP warm-started) | {_f(mpc_ms)} ms "
        f"(p95 {_f(_ms(mpc, 'p95_ms'))}) | {1000 * p['mpc_mean']:.0f} ± "
        f"{1000 * p['mpc_std']:.0f} ms |",
        f"| paper-style MPC (CVXPY, rebuilt each call; `expert.bench`) | {_f(base_ms, 1)} ms "
        f"(p95 {_f(_ms(mpc, 'baseline_p95_ms'), 1)}) | — |",
        f"| CNN + LSTM policy, shipped size{params(shipped)} | {_f(pol_ms)} ms "
        f"(p99 {_f(_ms(shipped, 'p99_ms'))}) | {1000 * p['policy_mean']:.1f} ± "
        f"{1000 * p['policy_std']:.1f} ms |",
        f"| paper-style CNN-MLP + LSTM-MLP (our reconstruction{params(style)}) | "
        f"{_f(style_ms)} ms (p99 {_f(_ms(style, 'p99_ms'))}) | — |",
        f"| **ratio MPC / policy** | {ratio(mpc_ms, pol_ms)} | {paper_ratio:.1f}× |",
        f"| ratio paper-style MPC / paper-style network | {ratio(base_ms, style_ms)} | — |",
    ]
    text = "\n".join(lines)
    if mpc_ms is not None and pol_ms is not None:
        if mpc_ms < pol_ms:
            text += (
                f"\n\nOur MPC expert is *faster* per step than our policy ({_f(mpc_ms)} ms vs "
                f"{_f(pol_ms)} ms), so the paper's {paper_ratio:.1f}× speed-up of the policy "
                "over the expert does not reproduce here: it comes from how the paper's MPC is "
                "solved. Solved the paper's way (the CVXPY row) the MPC takes "
                f"{_f(base_ms, 1)} ms, {ratio(base_ms, style_ms)} a paper-style network's time."
            )
        else:
            text += (
                f"\n\nOur policy is {ratio(mpc_ms, pol_ms)} faster per step than our MPC "
                f"(paper: {paper_ratio:.1f}×)."
            )
    text += (
        f"\n\nTimed in the run's eval stage on its machine (one thread, batch 1; "
        f"{pol.get('steps', '?')} policy steps, {mpc.get('samples', '?')} MPC solves, "
        f"{mpc.get('baseline_samples', '?')} CVXPY solves); the paper's figures are from its "
        "own hardware, so compare ratios, not milliseconds."
    )
    return text


def _standing(metrics: dict[str, Any]) -> tuple[str, tuple[bool, ...]]:
    rows = metrics["rows"]
    met = tuple(t.met(rows) for t in TARGETS)
    lines = ["| target | value | met |", "|---|---:|:---:|"]
    for t, ok in zip(TARGETS, met, strict=True):
        v = t.value(rows)
        shown = _pct(v) if t.unit == "%" else f"{_f(v)} {t.unit}"
        lines.append(f"| {t.describe()} | {shown} | {'yes' if ok else '**no**'} |")
    missed = [t.describe() for t, ok in zip(TARGETS, met, strict=True) if not ok]
    summary = f"**{sum(met)} of {len(TARGETS)} targets met.** " + (
        "Not met: " + "; ".join(missed) + "." if missed else "All targets are met."
    )
    return summary + "\n\n" + "\n".join(lines), met


def _trajectory_caption(traces: dict[str, _Trace], seed: int, episode: int) -> str:
    parts = []
    for row, tr in traces.items():
        state = "landed" if tr.landed else "timed out"
        if tr.eval_error_m is None:
            check = "no eval record for this episode"
        elif abs(tr.eval_error_m - tr.landing_error_m) <= 1e-6:
            check = "as in its eval episode"
        else:
            check = f"**eval recorded {_f(tr.eval_error_m)} m — this flight differs**"
        parts.append(f"{ROWS[row]} {state}, error {_f(tr.landing_error_m)} m ({check})")
    return f"Seed {seed}, episode {episode}: " + "; ".join(parts) + "."


# ------------------------------------------------------------------------------ entry point


class _Figures:
    """The report's figures in order: each PNG, and its markdown (image link + numbered caption)."""

    def __init__(self, out: Path, prov: _Provenance) -> None:
        self._base = out.parent
        self._prov = prov
        self.paths: list[Path] = []
        self.sections: list[str] = []

    def add(self, path: Path, alt: str, caption: str) -> None:
        self.paths.append(path)
        link = Path(os.path.relpath(path, self._base)).as_posix()
        self.sections.append(
            f"![{alt}]({link})\n\n*Figure {len(self.paths)}: {caption} {self._prov.caption()}*"
        )

    def say(self, text: str) -> None:
        self.sections.append(text)


def _add_trajectories(
    figs: _Figures,
    metrics: dict[str, Any],
    run: Path,
    episodes: tuple[int, ...],
    figdir: Path,
    prov: _Provenance,
) -> list[str]:
    """Fly ``episodes`` with the four policies, draw states and inputs; returns the flights
    that do not reproduce their eval record."""
    scenario = _scenario(metrics, run / "metrics.json")
    seed = int(metrics["eval_seed"])
    worst = _default_episodes(metrics)[-1]
    mismatches: list[str] = []
    for ep in episodes:
        traces = _fly_traces(metrics, run, ep, scenario)
        which = f"eval episode {ep}" + (
            " (the vision row's worst)" if ep == worst and ep != episodes[0] else ""
        )
        v = traces["vision"]
        title = (
            f"Seed {seed}, {which}; vision landing error {_f(v.landing_error_m)} m flown now, "
            f"{_f(v.eval_error_m)} m in metrics.json"
        )
        mismatches += [
            f"{row} episode {ep} ({_f(t.landing_error_m)} m now, {_f(t.eval_error_m)} m in "
            "metrics.json)"
            for row, t in traces.items()
            if t.eval_error_m is not None and abs(t.eval_error_m - t.landing_error_m) > 1e-6
        ]
        figs.add(
            _plot_states(traces, title, figdir / f"trajectory_states_ep{ep}.png", prov),
            f"states, episode {ep}",
            "state trajectories (ground-truth NED position, velocity, roll/pitch/yaw at each "
            f"10 Hz control step) of {which}, flown in process by all four policies — the "
            "paper's Figures 3 (expert), 6 (vision), 8 (BC) and 10 (DAgger) show this for many "
            "episodes. " + _trajectory_caption(traces, seed, ep),
        )
        figs.add(
            _plot_inputs(traces, title, figdir / f"trajectory_inputs_ep{ep}.png", prov),
            f"inputs, episode {ep}",
            "the inputs (Command: collective thrust_norm and FRD body rates) of the same flights "
            "— the paper's Figures 4, 7, 9 and 11 (its inputs are thrust and body torques; ours "
            "are the autopilot's rate setpoints).",
        )
    return mismatches


def _regenerate_eval(run: Path, metrics: dict[str, Any]) -> str:
    """The commands that rerun the eval stage of ``run`` (it skips a finished stage)."""
    profile = metrics["profile"].get("name", "PROFILE")
    return f"rm {run}/stages/eval.json && visland train eval --run {run} --profile {profile}"


def rollouts_text(prof: dict[str, Any]) -> str:
    """How a run's DAgger learner rollouts flew (its profile's ``rollouts`` key)."""
    how = prof.get("rollouts")
    if how == "mavlink":
        return (
            "flown by the learner through `visland sitl` + `visland companion` processes over "
            f"MAVLink/UDP in lockstep ({prof.get('workers', 1)} pairs side by side; the SITL's "
            "logs relabelled)"
        )
    if how == "inprocess":
        return "flown in process (the gymnasium env)"
    return "flown in process (the run predates the profile's `rollouts` key)"


def _header(
    cfg: ReportConfig, metrics: dict[str, Any], prov: _Provenance, mismatches: list[str] | None
) -> str:
    mpath = prov.run / "metrics.json"
    stages = metrics.get("stages") if isinstance(metrics.get("stages"), dict) else {}
    stage_commits = sorted(
        f"{name} `{_short(rec.get('git_commit'))}`"
        for name, rec in stages.items()
        if isinstance(rec, dict) and rec.get("git_commit")
    )
    if mismatches:
        reflown = (
            f"- **Re-flying does not reproduce the eval records**: {'; '.join(mismatches)}. "
            "Lockstep flights are meant to be bit-for-bit deterministic (DESIGN.md), so code, "
            "checkpoint or environment differ from what the eval stage flew; regenerate it "
            f"(`{_regenerate_eval(prov.run, metrics)}`) and this report.\n"
        )
    elif mismatches is not None:
        reflown = (
            "- Every trajectory flight below reproduces its eval record (landing error within "
            "1e-6 m).\n"
        )
    else:
        reflown = ""
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return f"""# visland results — paper Table 3, runtime and figures

> Generated by `{cfg.command()}` on {now}, code at `{prov.code_commit}`. Do not edit: every
> number and figure below is read from `{mpath}` (or computed from it, or flown from the run's
> checkpoints) by that command; the paper's numbers are constants in `training/report.py`
> citing the paper's sections. Rerun the command to regenerate.

- Run: `{prov.run}`, profile `{metrics["profile"].get("name", "?")}`, eval stage at commit
  `{prov.run_commit}`{"; stages: " + ", ".join(stage_commits) if stage_commits else ""}.
- {_seed_line(metrics)}
- DAgger learner rollouts: {rollouts_text(metrics["profile"])}.
{reflown}- Success = landing error ≤ 1 m, vertical touchdown speed ≤ 1 m/s, tilt ≤ 20°;
  touchdown speed in the table is the norm of the velocity at first contact (DESIGN.md,
  Metrics).
"""


def write_report(cfg: ReportConfig) -> ReportResult:
    """Write ``cfg.out`` and its figures from ``<cfg.run>/metrics.json``; see the module doc.

    Raises:
        ReportError: the run folder, ``metrics.json`` or a field of it is missing or malformed,
            or a checkpoint or scenario needed for the trajectory flights is gone.
    """
    run = Path(cfg.run)
    metrics = load_metrics(run)
    mpath = run / "metrics.json"
    out = Path(cfg.out)
    figdir = cfg.figures()
    prov = _Provenance(
        cfg.command(), _code_commit(), run, str(metrics.get("git_commit") or "unknown")
    )
    episodes = tuple(dict.fromkeys(cfg.trajectory_episodes or _default_episodes(metrics)))
    if any(e < 0 for e in episodes):
        raise ReportError(f"trajectory episodes must be >= 0, got {episodes}")
    if cfg.trajectories:
        _scenario(metrics, mpath)  # fail before any file is touched

    figdir.mkdir(parents=True, exist_ok=True)
    for pattern in _FIGURE_PATTERNS:  # a figure this report no longer makes must not linger
        for old in figdir.glob(pattern):
            old.unlink()
    figs = _Figures(out, prov)
    notes: list[str] = []

    mismatches = None
    if cfg.trajectories:
        mismatches = _add_trajectories(figs, metrics, run, episodes, figdir, prov)
    else:
        figs.say(
            "Trajectory figures were skipped (`--no-trajectories`); run "
            f"`visland report --run {run}` to fly and draw them."
        )

    touch = _touchdowns(metrics)
    if sum(len(ne) for ne, _, _ in touch.values()) == 0:
        note = (
            f"**Landing scatter unavailable for this run**: `{mpath}` has no "
            "`per_episode[*].touchdown_ne_m` (the run was evaluated before touchdown positions "
            f"were recorded). Regenerate the eval stage with `{_regenerate_eval(run, metrics)}`, "
            f"then rerun `{cfg.command()}`."
        )
        notes.append(note)
        figs.say(note)
    else:
        lacking = sum(k for _, _, k in touch.values())
        figs.add(
            _plot_scatter(metrics, figdir / "landing_scatter.png", prov),
            "landing scatter",
            "touchdown positions (east, north) around the pad of every eval episode, per policy; "
            f"green = success, red = failure; ▲ on the border = beyond ±{_SCATTER_VIEW_M:g} m, "
            "in its direction."
            + (f" {lacking} episodes have no recorded position, not drawn." if lacking else ""),
        )

    figs.add(
        _plot_hist(metrics, figdir / "landing_error_hist.png", prov),
        "landing error histogram",
        "landing error of every eval episode, log-spaced bins; dotted lines = the paper's "
        "Table 3 means.",
    )
    loss = _plot_loss(_loss_series(run), figdir / "training_loss.png", prov)
    if loss is not None:
        figs.add(
            loss,
            "training loss",
            f"controller training loss from `{run}/scalars.jsonl`; dotted lines mark where "
            "learner rollouts, relabelled by the expert, were aggregated (the paper's Figure 5).",
        )

    standing, met = _standing(metrics)
    md = (
        f"""{_header(cfg, metrics, prov, mismatches)}
## Where we stand

{standing}

## Table 3 — landing performance, ours beside the paper (paper §5.4)

{_table3(metrics)}

The paper's Table 3 has landing error only and no expert row; its LSTM-only rows are
privileged (true position and velocity), as ours are. Numbers: {prov.caption()}

## Runtime — MPC vs policy per control step (paper §6)

{_runtime(metrics, mpath)}

## Figures

"""
        + "\n\n".join(figs.sections)
        + "\n"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(md)
    return ReportResult(
        out=out,
        figures=tuple(figs.paths),
        targets_met=met,
        standing=standing.split("\n", 1)[0],
        notes=tuple(notes),
    )
