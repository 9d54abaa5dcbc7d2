"""The report's figures: trajectory flights of the run's four policies (one eval episode,
re-flown in process and checked against its eval record), states and inputs over time, the
landing scatter, the landing-error histogram and the training-loss curves. Each PNG carries
the command and commits that made it in a footer."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from training.paper import PAPER_TABLE3
from training.report.metrics import ROWS, Provenance, ReportError
from training.stage_records import Metrics

__all__ = [
    "FIGURE_PATTERNS",
    "SCATTER_VIEW_M",
    "Trace",
    "default_episodes",
    "draw_pad",
    "fly_traces",
    "loss_series",
    "plot_hist",
    "plot_inputs",
    "plot_loss",
    "plot_scatter",
    "plot_states",
    "scenario_of",
    "touchdowns",
]

_COLORS = {"expert": "k", "bc": "tab:orange", "dagger": "tab:blue", "vision": "tab:green"}
SCATTER_VIEW_M = 3.0  # half-width of the scatter's view: the 4 m pad plus a margin
FIGURE_PATTERNS = (
    "trajectory_*.png",
    "landing_scatter.png",
    "landing_error_hist.png",
    "training_loss.png",
)
"""Every PNG this module writes (a report removes stale ones first)."""


# ------------------------------------------------------------------------------ trajectories


@dataclass
class Trace:
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

    def __init__(self, policy: Any, trace: Trace) -> None:
        from sitl_sim.physics.dynamics import euler_from_quat

        self._policy = policy
        self._trace = trace
        self._euler = euler_from_quat
        self.privileged = bool(getattr(policy, "privileged", False))

    def initial_state(self) -> Any:
        return self._policy.initial_state()

    def for_vehicle(self, vehicle: Any) -> _Recording:
        """Record the pilot that flies ``vehicle`` (``training.exec.rollout.episode_pilot``)."""
        from training.exec.rollout import episode_pilot

        pilot = episode_pilot(self._policy, vehicle)
        return self if pilot is self._policy else _Recording(pilot, self._trace)

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


def scenario_of(metrics: Metrics, path: Path) -> str | None:
    """The scenario file the eval stage flew (None: the repository's default)."""
    s = metrics.rows.expert.scenario
    if s == "configs/scenario.toml" and not Path(s).is_file():
        return None  # the repository's default scenario, wherever the report runs from
    if not Path(s).is_file():
        raise ReportError(
            f"{path}: field rows.expert.scenario: scenario file {s!r} not found "
            "(run the report from the folder the pipeline ran in, or use --no-trajectories)"
        )
    return s


def _policy_source(metrics: Metrics, run: Path, row: str) -> str:
    """The policy the eval stage flew for ``row``: ``expert`` or its checkpoint file."""
    name = metrics.rows[row].policy
    if name == "expert":
        return name
    candidates = [Path(name), run / "checkpoints" / Path(name).name]
    for c in candidates:
        if c.is_file():
            return str(c)
    raise ReportError(
        f"{run / 'metrics.json'}: field rows.{row}.policy: checkpoint {name!r} not "
        f"found (nor {candidates[-1]}); restore the run's checkpoints or use --no-trajectories"
    )


def fly_traces(metrics: Metrics, run: Path, episode: int, scenario: str | None) -> dict[str, Trace]:
    from companion.policy_net import load_policy
    from sitl_sim.env import LandingEnv
    from training.exec.rollout import fly_episode, make_policy

    seed = metrics.eval_seed
    traces = {}
    for row in ROWS:
        source = _policy_source(metrics, run, row)
        trace = Trace(row)
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
            e for e in metrics.rows[row].per_episode if e.episode == episode and e.seed == seed
        ]
        if match:
            trace.eval_error_m = match[0].landing_error_m
        traces[row] = trace
    return traces


def default_episodes(metrics: Metrics) -> tuple[int, ...]:
    """Episode 0 (the first) and the vision row's worst episode."""
    rows = metrics.rows.vision.per_episode
    eps = [e for e in rows if e.landing_error_m is not None]
    first = min((e.episode for e in rows), default=0)
    if not eps:
        return (first,)
    worst = max(eps, key=lambda e: e.landing_error_m or 0.0).episode
    return (first,) if worst == first else (first, worst)


# ------------------------------------------------------------------------------ figures


def _plt():
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path, prov: Provenance, footer_h: float) -> Path:
    """Lay ``fig`` out above a band ``footer_h`` high (figure fraction), write the provenance
    footer in it, save the PNG and close the figure."""
    fig.tight_layout(rect=(0, footer_h, 1, 1))
    fig.text(0.005, 0.003, prov.footer(), fontsize=6, color="0.35", ha="left", va="bottom")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80, pil_kwargs={"optimize": True})
    _plt().close(fig)
    return path


def plot_states(traces: dict[str, Trace], title: str, path: Path, prov: Provenance) -> Path:
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
    return _finish_time_panels(fig, axes, title, path, prov)


def _finish_time_panels(fig: Any, axes: Any, title: str, path: Path, prov: Provenance) -> Path:
    """Time axis label on the bottom row, one legend, title; saved with the provenance line."""
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=9)
    return _save(fig, path, prov, 0.02)


def plot_inputs(traces: dict[str, Trace], title: str, path: Path, prov: Provenance) -> Path:
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
    return _finish_time_panels(fig, axes, title, path, prov)


def draw_pad(ax: Any, success_circle: bool = True) -> None:
    """The pad (``sitl_sim.render.scene.PadGeometry``: green square, red cross) at the origin of a
    top
    view (x east, y north), and the success radius as a dashed circle."""
    from matplotlib.patches import Circle, Rectangle

    from sitl_sim.metrics import SUCCESS_MAX_ERROR_M
    from sitl_sim.render.scene import PadGeometry

    pad = PadGeometry()
    s, a, w = pad.side_m / 2, pad.cross_length_m / 2, pad.cross_width_m / 2
    ax.add_patch(Rectangle((-s, -s), 2 * s, 2 * s, color=pad.green_rgb, alpha=0.35, zorder=0))
    ax.add_patch(Rectangle((-a, -w), 2 * a, 2 * w, color=pad.red_rgb, alpha=0.35, zorder=0))
    ax.add_patch(Rectangle((-w, -a), 2 * w, 2 * a, color=pad.red_rgb, alpha=0.35, zorder=0))
    if success_circle:
        ax.add_patch(Circle((0, 0), SUCCESS_MAX_ERROR_M, fill=False, linestyle="--", color="0.3"))


def touchdowns(metrics: Metrics) -> dict[str, tuple[np.ndarray, np.ndarray, int]]:
    """Per row: (N x 2 north/east, success flags, episodes lacking a position)."""
    out = {}
    for row in ROWS:
        eps = metrics.rows[row].per_episode
        have = [e for e in eps if e.touchdown_ne_m is not None]
        ne = np.array([e.touchdown_ne_m for e in have], dtype=float).reshape(-1, 2)
        ok = np.array([e.success for e in have], dtype=bool)
        out[row] = (ne, ok, len(eps) - len(have))
    return out


def plot_scatter(metrics: Metrics, path: Path, prov: Provenance) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(10, 10))
    view = SCATTER_VIEW_M
    for ax, (row, (ne, ok, lacking)) in zip(axes.flat, touchdowns(metrics).items(), strict=True):
        draw_pad(ax)
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
        f"Touchdown positions around the pad, {metrics.episodes} eval episodes per policy "
        f"(seed {metrics.eval_seed}); dashed circle = 1 m success radius",
        fontsize=10,
    )
    return _save(fig, path, prov, 0.02)


def plot_hist(metrics: Metrics, path: Path, prov: Provenance) -> Path:
    plt = _plt()
    errs = {
        row: np.array(
            [
                e.landing_error_m
                for e in metrics.rows[row].per_episode
                if e.landing_error_m is not None
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
        f"Landing error per eval episode (seed {metrics.eval_seed}); errors below "
        f"{lo:g} m are counted in the first bin",
        fontsize=10,
    )
    return _save(fig, path, prov, 0.03)


def loss_series(run: Path) -> dict[str, list[tuple[int, float]]]:
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


def plot_loss(
    series: dict[str, list[tuple[int, float]]], path: Path, prov: Provenance
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
    return _save(fig, path, prov, 0.03)
