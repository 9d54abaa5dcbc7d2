"""Companion latency: frame receipt -> setpoint handed to the OS, read from companion logs.

``visland bench companion [--checkpoint CKPT] [--runtime torch|onnx]`` flies (``visland
fly``: SITL + companion processes, lockstep, camera rendered) the checkpoint — by default the
shipped ``models/visland_vision.pt`` — with the chosen policy backend, and reads the latency
of every sent policy command from the companion's logs: median / p90 / p99 / max, and the
policy's share of it. ``runtime = onnx`` exports the checkpoint first (into the run folder, so
nothing is written beside the checkpoint).

In the same run, the first flight's recorded frames and telemetry are replayed in this process
through *both* backends, one thread each, alternating (:func:`compare_runtimes`): the per-step
policy time of torch and ONNX Runtime on identical inputs — a fair ratio even on a shared,
noisy machine — and how far each backend's commands are from the ones flown.

``python -m tools.bench_companion LOG...`` reads existing companion logs instead;
``--policy untrained`` flies a randomly initialised network of the shipped size (what the
latency depends on) and ``--policy expert`` the MPC.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.record import latency_stats
from tools.cli_args import print_json

__all__ = ["bench_companion", "compare_runtimes", "format_bench", "main", "print_bench"]


class _Timed:
    """A Policy that records the wall time of each ``act`` of the policy it wraps."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.privileged = bool(getattr(policy, "privileged", False))
        self.samples: list[float] = []

    def initial_state(self) -> Any:
        return self.policy.initial_state()

    def act(self, observation: Any, groundtruth: Any, state: Any):
        t0 = time.perf_counter()
        out = self.policy.act(observation, groundtruth, state)
        self.samples.append(time.perf_counter() - t0)
        return out


def compare_runtimes(checkpoint: str | Path, log: str | Path, rounds: int = 2) -> dict[str, Any]:
    """Replay ``log`` (a companion log of ``checkpoint``) through the torch and the ONNX
    backend, one intra-op thread each, ``rounds`` times alternating. ONNX graphs must be
    beside the checkpoint (``visland export-onnx``).

    Returns per backend the policy step median / p99 (ms) over every replayed step, and the
    largest |difference| of its commands from the recorded ones (the backend that flew the log
    gives its own commands back; the other shows how far the two backends are apart).
    """
    from companion.record import replay_log
    from companion.runtime import PolicyRuntime, load_policy_file

    policies = {name: load_policy_file(checkpoint, 1, name) for name in ("torch", "onnx")}
    samples: dict[str, list[float]] = {name: [] for name in policies}
    diffs: dict[str, float] = {}
    steps: dict[str, int] = {}
    for _ in range(rounds):
        for name, policy in policies.items():
            runtime = PolicyRuntime(policy, name)
            error = runtime.warm_up()
            if error is not None:
                raise ValueError(f"{checkpoint} ({name}): fails on a synthetic hover: {error}")
            timed = _Timed(policy)
            report = replay_log(log, PolicyRuntime(timed, name))
            if report.errors:
                raise ValueError(f"replay of {log} with {name}: {report.errors[:3]}")
            samples[name] += timed.samples
            diffs[name] = max(diffs.get(name, 0.0), report.max_abs_diff)
            steps[name] = report.commands
    out: dict[str, Any] = {"log": str(log), "rounds": rounds, "threads": 1}
    for name, values in samples.items():
        arr = np.asarray(values) * 1e3
        out[name] = {
            "steps": steps[name],
            "median_ms": float(np.median(arr)),
            "p99_ms": float(np.percentile(arr, 99)),
            "max_abs_diff_vs_flown": diffs[name],
        }
    out["onnx_speedup"] = out["torch"]["median_ms"] / out["onnx"]["median_ms"]
    return out


def bench_companion(
    logs: list[Path] | None = None,
    policy: str = "untrained",
    episodes: int = 3,
    seed: int = 0,
    scenario: str | None = None,
    runtime: str = "torch",
    compare: bool = True,
    live: bool = False,
    scene_baseline: bool = False,
) -> dict[str, Any]:
    """Latency figures from ``logs``, or from a fresh ``fly`` run of ``policy`` on ``runtime``
    (``torch`` | ``onnx``); with ``compare`` and a checkpoint file, also
    :func:`compare_runtimes` on the run's first flight. With ``live``, the same flights again
    with the live view on and a Foxglove-protocol client subscribed to every channel
    (:mod:`tools.live_client`): ``live`` holds their latency and ``live_vs_off`` the ratios of
    median and p99 (with a viewer / without). With ``scene_baseline``, the same flights again
    with ``--log-scene off``: ``scene_off`` holds their latency and log size, and
    ``scene_vs_off`` the ratios (the default ``auto`` writes the live view's picture into each
    log after each answer: what that costs)."""
    if logs:
        return {"logs": [str(p) for p in logs], **latency_stats(list(logs))}
    from companion.runtime import RUNTIMES
    from training.exec.fly import FlyConfig, fly

    if runtime not in RUNTIMES:
        raise ValueError(f"runtime = {runtime!r}; expected one of {RUNTIMES}")
    is_file = policy not in ("untrained", "untrained-privileged", "expert", "cascade")
    if is_file and not Path(policy).is_file():
        raise FileNotFoundError(f"{policy}: no such checkpoint file")
    if runtime == "onnx" and not is_file:
        raise ValueError(f"--runtime onnx needs a checkpoint file, not {policy!r}")
    run = Path(tempfile.mkdtemp(prefix="visland_bench_companion_"))
    flown = Path(policy)
    if is_file and (runtime == "onnx" or compare):
        # the ONNX graphs are exported beside a copy, never beside the user's checkpoint
        from companion.onnx_export import export_onnx

        flown = run / "policy" / Path(policy).name
        flown.parent.mkdir(parents=True)
        shutil.copyfile(policy, flown)
        export_onnx(flown)

    def flights(folder: str, *companion_args: str) -> tuple[Any, list[Path]]:
        report = fly(
            FlyConfig(
                policy=str(flown) if is_file else policy,
                episodes=episodes,
                seed=seed,
                scenario=scenario,
                render=True,
                progress=False,
                out=str(run / folder),
                companion_args=("--runtime", runtime, *companion_args),
            )
        )
        return report, sorted((Path(report.out) / "companion").glob("*.mcap"))

    report, logs = flights("fly")
    baseline = None
    if scene_baseline:
        plain, plain_logs = flights("scene_off", "--log-scene", "off")
        baseline = {"success_rate": plain.summary.success_rate, **_with_size(plain_logs)}
    watched = None
    if live:
        watched = _fly_watched(
            str(flown) if is_file else policy, episodes, seed, scenario, runtime, run / "live"
        )
    res: dict[str, Any] = {
        "policy": policy,
        "runtime": runtime,
        "episodes": episodes,
        "seed": seed,
        "success_rate": report.summary.success_rate,
        "run": str(run),
        **_with_size(logs),
    }
    if is_file and compare and logs:
        res["compare"] = compare_runtimes(flown, logs[0])
    if baseline is not None:
        res["scene_off"] = baseline
        res["scene_vs_off"] = {
            k: res[k] / baseline[k] if baseline.get(k) else None
            for k in ("median_ms", "p99_ms", "log_bytes_per_flight")
        }
    if watched is not None:
        res["live"] = watched
        res["live_vs_off"] = {
            k: watched[f"{k}_ms"] / res[f"{k}_ms"] if res.get(f"{k}_ms") else None
            for k in ("median", "p99")
        }
    return res


def _with_size(logs: list[Path]) -> dict[str, Any]:
    """:func:`latency_stats` of ``logs`` and their mean size."""
    size = sum(p.stat().st_size for p in logs) / len(logs) if logs else None
    return {**latency_stats(list(logs)), "log_bytes_per_flight": size}


def _fly_watched(
    policy: str, episodes: int, seed: int, scenario: str | None, runtime: str, out: Path
) -> dict[str, Any]:
    """The same flights with ``--live`` and a client subscribed to every channel throughout:
    the companion's latency then, and what the client received."""
    import socket
    import threading

    from tools.live_client import watch
    from training.exec.fly import FlyConfig, fly

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    done = threading.Event()
    seen: dict[str, Any] = {}

    def client() -> None:
        topics = {"/camera/image", "/scene", "/camera/annotations", "/tf", "/live/state"}
        got = watch(port, topics, per_topic=10**9, timeout_s=600.0, until=done.is_set)
        seen["messages"] = {t: len(m) for t, m in got.messages.items()}

    viewer = threading.Thread(target=client, daemon=True)
    viewer.start()
    report = fly(
        FlyConfig(
            policy=policy,
            episodes=episodes,
            seed=seed,
            scenario=scenario,
            render=True,
            progress=False,
            out=str(out),
            live=str(port),
            companion_args=("--runtime", runtime),
        )
    )
    done.set()
    viewer.join(30)
    logs = sorted((Path(report.out) / "companion").glob("*.mcap"))
    return {
        "success_rate": report.summary.success_rate,
        "received": seen.get("messages", {}),
        **latency_stats(list(logs)),
    }


def format_bench(res: dict[str, Any]) -> str:
    """The human-readable lines of a :func:`bench_companion` result."""
    where = f"runtime {res['runtime']}, {res['policy']}, " if "runtime" in res else ""
    lines = [
        f"frame receipt -> setpoint sent ({where}{res['commands']} commands"
        + (f", {res['episodes']} episodes" if "episodes" in res else "")
        + f"): median {res['median_ms']:.2f} ms, p90 {res['p90_ms']:.2f} ms, "
        f"p99 {res['p99_ms']:.2f} ms, max {res['max_ms']:.2f} ms "
        f"(policy: median {res['policy_median_ms']:.2f} ms, p99 {res['policy_p99_ms']:.2f} ms)"
    ]
    cmp = res.get("compare")
    if cmp:
        t, o = cmp["torch"], cmp["onnx"]
        lines.append(
            f"same run, the first flight's {t['steps']} frames replayed here, one thread: "
            f"policy step torch median {t['median_ms']:.3f} ms (p99 {t['p99_ms']:.3f}), "
            f"onnx median {o['median_ms']:.3f} ms (p99 {o['p99_ms']:.3f}) -> onnx "
            f"{cmp['onnx_speedup']:.2f}x faster"
        )
        lines.append(
            f"commands vs the flown ones ({res['runtime']}): torch max |diff| "
            f"{t['max_abs_diff_vs_flown']:.2g}, onnx max |diff| {o['max_abs_diff_vs_flown']:.2g}"
        )
    lines += [line(res) for key, line in _VERSUS if res.get(key)]
    return "\n".join(lines)


def _scene_off_line(res: dict[str, Any]) -> str:
    plain, ratio = res["scene_off"], res["scene_vs_off"]
    return (
        f"the same flights with --log-scene off: {_latency(plain)}, "
        f"{plain['log_bytes_per_flight'] / 1e6:.2f} MB a log (with the scene: "
        f"{_times(ratio['median_ms'], ratio['p99_ms'])}, x{ratio['log_bytes_per_flight']:.2f} "
        "log size)"
    )


def _live_line(res: dict[str, Any]) -> str:
    watched, ratio = res["live"], res["live_vs_off"]
    return (
        "the same flights with the live view and a client subscribed to every channel: "
        f"{_latency(watched)} ({_times(ratio['median'], ratio['p99'])} of the flights without; "
        f"the client received {sum(watched['received'].values())} messages)"
    )


_VERSUS = (("scene_off", _scene_off_line), ("live", _live_line))
"""The comparison runs a result may hold (its key) and the line each prints."""


def _latency(stats: dict[str, Any]) -> str:
    """``median … ms, p99 … ms`` of a :func:`latency_stats` result."""
    return f"median {stats['median_ms']:.2f} ms, p99 {stats['p99_ms']:.2f} ms"


def _times(median: float, p99: float) -> str:
    """A run's median and p99 as multiples of another's."""
    return f"x{median:.2f} median, x{p99:.2f} p99"


def print_bench(res: dict[str, Any], as_json: bool, prog: str) -> int:
    """Print a :func:`bench_companion` result (one JSON document, or :func:`format_bench`'s
    lines); the exit code: 1 when no policy command was sent (nothing to time), else 0."""
    if as_json:
        print_json(res)
        return 0
    if not res.get("commands"):
        print(f"{prog}: no sent policy commands", file=sys.stderr)
        return 1
    print(format_bench(res))
    return 0


def main(argv: list[str] | None = None) -> int:
    from training.exec.fly import FlyError

    p = argparse.ArgumentParser(prog="python -m tools.bench_companion", description=__doc__)
    p.add_argument("logs", nargs="*", type=Path, help="companion MCAP logs (none: fly first)")
    p.add_argument("--policy", default="untrained", help="untrained | expert | checkpoint")
    p.add_argument("--runtime", choices=("torch", "onnx"), default="torch")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scenario", default=None)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    try:
        res = bench_companion(
            args.logs, args.policy, args.episodes, args.seed, args.scenario, args.runtime
        )
    except (ValueError, OSError) as exc:
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 2
    except FlyError as exc:
        print(f"{p.prog}: failed: {exc}", file=sys.stderr)
        return 1
    return print_bench(res, args.json, p.prog)


if __name__ == "__main__":
    sys.exit(main())
