"""``visland sitl``, ``companion``, ``fly``, ``demo`` and ``readme``: the SITL and the companion,
alone or flown together as separate processes over MAVLink/UDP. Thin shells over
:func:`sitl_sim.mavlink.sitl.run_sitl`, :func:`companion.app.run_from_args`,
:func:`training.exec.fly.fly`, :func:`tools.demo.run` and :func:`tools.readme.run` (the
README's demo block, from a demo run)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

from tools.cli_args import (
    add_deprecated_alias,
    add_episode_arguments,
    add_live_argument,
    config_from_args,
    json_command,
    print_json,
    scenario_arg,
)
from training.seeds import EVAL_SEED

__all__ = ["cmd_fly", "register_sim"]


class _LinkFlag(NamedTuple):
    """One ``visland fly`` flag that impairs the link: the SITL's flag of the same name
    (``sitl_sim.mavlink.config``), and its old ``fly`` spelling, if it had another."""

    dest: str
    metavar: str
    help: str
    deprecated: str | None = None

    @property
    def flag(self) -> str:
        return "--" + self.dest.replace("_", "-")


_LINK_FLAGS = (
    _LinkFlag("link_loss_prob", "P", "loss probability", "--link-loss"),
    _LinkFlag("link_delay_ms", "D", "fixed one-way delay, ms"),
    _LinkFlag("link_jitter_ms", "J", "extra delay uniform in [0, J] ms (each stream in order)"),
    _LinkFlag("link_duplicate_prob", "P", "duplicate probability", "--link-duplicate"),
    _LinkFlag(
        "link_reorder_prob",
        "P",
        "probability a datagram jumps the queue (needs a delay)",
        "--link-reorder",
    ),
    _LinkFlag("link_cut_at_s", "T", "the link dies for good T s into each flight (failsafe test)"),
)
"""``visland fly``'s impaired-link flags, named as ``visland sitl``'s, in ``--help`` order."""


def _link_sitl_args(args: argparse.Namespace) -> tuple[str, ...]:
    """The SITL flags for the ``--link-*`` flags given (none given: none)."""
    out: list[str] = []
    for flag in _LINK_FLAGS:
        value = getattr(args, flag.dest, None)
        if value is not None:
            out += [flag.flag, repr(float(value))]
    return tuple(out)


def _cmd_demo(args: argparse.Namespace) -> int:
    from tools.demo import DemoConfig, run
    from training.exec.fly import FlyError

    # With --json the narration goes to stderr so stdout is one JSON document.
    narration = sys.stderr if args.json else sys.stdout
    try:
        report = run(config_from_args(DemoConfig, args, progress=not args.json), narration)
    except FlyError as exc:
        print(f"visland demo: failed: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print_json(report)
    return 0  # failed landings are results, reported above, not errors of the demo


def _cmd_sitl(args: argparse.Namespace) -> int:
    import logging

    from sitl_sim.mavlink.config import sitl_config_from_args
    from sitl_sim.mavlink.sitl import run_sitl

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cfg = sitl_config_from_args(args)
    logging.getLogger("visland.sitl").info(
        "scenario %s, seed %d, episodes %d..%d",
        cfg.scenario or "configs/scenario.toml",
        cfg.seed,
        cfg.first_episode,
        cfg.first_episode + cfg.episodes - 1,
    )
    return run_sitl(cfg)


def _cmd_companion(args: argparse.Namespace) -> int:
    import logging

    from companion.app import run_from_args
    from training.companion_process import resolve_policy

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    return run_from_args(args, resolve_policy, "visland companion")


def _register_install_service(companion: argparse.ArgumentParser) -> None:
    """``visland companion install-service``: :mod:`companion.install_service`."""
    from companion.install_service import __doc__ as doc
    from companion.install_service import add_arguments, run_from_args

    sub = companion.add_subparsers(dest="companion_command", metavar="install-service")
    ins = sub.add_parser(
        "install-service",
        help="set this board up to run the companion as a systemd service (docs/deploy.md)",
        description=doc.split("\n\n")[0],
    )
    add_arguments(ins)
    ins.set_defaults(func=run_from_args)


def cmd_fly(args: argparse.Namespace) -> int:
    """``visland fly``, and ``visland eval --transport mavlink`` (whose ``--workers`` are fly's
    ``--instances``; the flags only fly has take their defaults)."""
    from training.evaluate import format_table
    from training.exec.choose import backend_from_args
    from training.exec.fly import DEFAULT_VISION_POLICY, FlyConfig, FlyError, fly
    from training.exec.fly_many import fly_many

    link_args = _link_sitl_args(args)
    if link_args and not getattr(args, "realtime", False):
        print(
            f"visland {args.command}: --link-* impair a real-time link; add --realtime "
            "(in lockstep a delayed answer would stop the clock instead of arriving late)",
            file=sys.stderr,
        )
        return 2
    mode = getattr(args, "companion_mode", "offboard")
    policy = args.policy
    if policy is None:  # fly's default: the expert flies; in landing-target mode, the shipped net
        policy = DEFAULT_VISION_POLICY if mode == "landing-target" else "expert"
    cfg = FlyConfig(
        policy=policy,
        companion_mode=mode,
        episodes=args.episodes,
        seed=args.seed,
        scenario=scenario_arg(args),
        realtime=getattr(args, "realtime", False),
        out=str(args.out) if getattr(args, "out", None) else None,
        progress=not args.json,
        sitl_args=link_args,
        autopilot=getattr(args, "autopilot", "px4"),
        sitl_params=tuple(getattr(args, "param", None) or ()),
        live=getattr(args, "live", ""),
        scene=getattr(args, "scene", False),
    )
    # eval --transport mavlink --workers N = fly --instances N
    instances = getattr(args, "instances", None) or getattr(args, "workers", 1)
    if instances < 1:
        print(f"visland {args.command}: --instances must be >= 1, got {instances}", file=sys.stderr)
        return 2
    try:
        if instances == 1 and args.ray is None:
            report = fly(cfg)
        else:
            with backend_from_args(args, instances) as backend:
                report = fly_many(cfg, list(range(args.episodes)), instances, backend=backend)
    except FlyError as exc:
        print(f"visland {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print_json(report)
    else:
        format_table(report, sys.stdout)
        lat = report.latency_ms
        if lat.get("commands"):
            print(
                f"  frame receipt -> setpoint sent: median {lat['median_ms']:.2f} ms, "
                f"p99 {lat['p99_ms']:.2f} ms over {lat['commands']} commands; logs in "
                f"{report.out}"
            )
    return 0


def _register_demo(sub: argparse._SubParsersAction) -> None:
    from training.provenance import SHIPPED_MODEL

    d = sub.add_parser(
        "demo",
        help="the shipped vision policy flies 3 landings: SITL + companion over MAVLink, "
        "results table, MCAP logs, PNG",
        description="Start the SITL and the companion as two processes over MAVLink/UDP, fly "
        "the shipped vision policy through N landings (lockstep), then print one row per "
        "landing, the MCAP flight logs of both processes and a PNG of all flights. Exit 0 when "
        "every episode was flown, whatever the landings scored (failures are reported); 1 when "
        "a process failed; 2 on bad input.",
    )
    add_live_argument(d, "the companion serves it: its camera, CNN and estimate beside the truth")
    d.add_argument(
        "--policy",
        default=str(SHIPPED_MODEL),
        help="checkpoint path, or expert | cascade (default: the shipped model, "
        "models/visland_vision.pt of this repository)",
    )
    add_episode_arguments(
        d,
        episodes=3,
        seed=EVAL_SEED,
        episodes_help="landings to fly (default 3)",
        seed_help=f"scenario seed: episodes 0..N-1 of it are flown (default {EVAL_SEED}, the "
        "evaluation seed, disjoint from training)",
    )
    d.add_argument(
        "--out",
        type=Path,
        default=Path("runs/demo"),
        help="output folder: logs, flights.png, demo.json; a previous demo there is replaced "
        "(default runs/demo)",
    )
    json_command(d, _cmd_demo, "print the report as JSON on stdout")


def _cmd_readme(args: argparse.Namespace) -> int:
    from tools.readme import ReadmeConfig, run
    from training.exec.fly import FlyError

    try:
        run(config_from_args(ReadmeConfig, args), sys.stdout)
    except FlyError as exc:
        print(f"visland readme: failed: {exc}", file=sys.stderr)
        return 1
    return 0


def _register_readme(sub: argparse._SubParsersAction) -> None:
    from tools.readme import ReadmeConfig

    defaults = ReadmeConfig()
    r = sub.add_parser(
        "readme",
        help="fly the demo and rewrite the README's demo output block and picture from it",
        description="Fly `visland demo` with the shipped model (or read a finished demo's "
        "demo.json), copy its flights.png to the README's picture and rewrite only the README's "
        "regions between the <!-- demo-picture:start/end --> and <!-- demo-output:start/end --> "
        "markers, naming the model's path and sha256. `make readme` runs it.",
    )
    r.add_argument("--readme", type=Path, default=defaults.readme, help="README to rewrite")
    r.add_argument(
        "--picture",
        type=Path,
        default=defaults.picture,
        help="where the demo's flights.png goes (default docs/demo_flights.png)",
    )
    r.add_argument(
        "--policy", default=defaults.policy, help="checkpoint to fly (default: the shipped model)"
    )
    r.add_argument(
        "--episodes", type=int, default=defaults.episodes, help="landings to fly (default 3)"
    )
    r.add_argument(
        "--out", type=Path, default=defaults.out, help="the demo's output folder (runs/demo)"
    )
    r.add_argument(
        "--from-json",
        type=Path,
        default=None,
        help="a finished demo's demo.json to write from instead of flying",
    )
    r.set_defaults(func=_cmd_readme)


def _cmd_soak(args: argparse.Namespace) -> int:
    from tools.soak import SoakConfig, format_soak, soak
    from training.exec.fly import FlyError

    cfg = config_from_args(SoakConfig, args, scenario=scenario_arg(args), progress=not args.json)
    try:
        report = soak(cfg)
    except FlyError as exc:
        print(f"visland soak: failed: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print_json(report.to_dict())
    else:
        print(format_soak(report))
    return 0 if report.ok else 1


def _register_soak(sub: argparse._SubParsersAction) -> None:
    sk = sub.add_parser(
        "soak",
        help="a field day: one companion process through many lockstep flights; its memory, "
        "descriptors and latency judged (exit 1 when one fails)",
    )
    sk.add_argument("--flights", type=int, default=500, help="consecutive flights (default 500)")
    sk.add_argument(
        "--policy", default="expert", help="what the companion flies (default: expert, no camera)"
    )
    sk.add_argument(
        "--warmup", type=int, default=20, help="flights before the baseline (default 20)"
    )
    sk.add_argument("--scenario", type=Path, default=None, help="scenario TOML (default nominal)")
    sk.add_argument("--seed", type=int, default=EVAL_SEED, help=f"seed (default {EVAL_SEED})")
    sk.add_argument("--out", default=None, help="run folder (default: a temporary one)")
    json_command(sk, _cmd_soak)


def _register_fly(sub: argparse._SubParsersAction) -> None:
    from training.exec.choose import add_backend_arguments

    fl = sub.add_parser(
        "fly", help="SITL + companion as separate processes over UDP: N episodes, eval JSON"
    )
    fl.add_argument(
        "--policy",
        default=None,
        help="expert | cascade | checkpoint path (default: expert; with --companion-mode "
        "landing-target: models/visland_vision.pt)",
    )
    fl.add_argument(
        "--companion-mode",
        choices=("offboard", "landing-target"),
        default="offboard",
        help="offboard: the companion flies the policy; landing-target: it streams "
        "LANDING_TARGET from the policy's camera estimator and the SITL's AUTO.PRECLAND lands",
    )
    fl.add_argument(
        "--autopilot",
        choices=("px4", "ardupilot"),
        default="px4",
        help="autopilot profile of the SITL and the companion; ardupilot sets GUID_OPTIONS=8 "
        "(offboard) or PLND_ENABLED=1,PLND_TYPE=1 (landing-target) on the SITL first",
    )
    fl.add_argument(
        "--param",
        action="append",
        metavar="NAME=VALUE",
        help="a SITL parameter set at start, after the profile's setup, as `visland sitl "
        "--param` (repeatable, each NAME=VALUE or NAME=VALUE,NAME=VALUE), e.g. GUID_OPTIONS=0 "
        "to see the companion refuse",
    )
    add_deprecated_alias(fl, "--sitl-param", "--param", "param", append=True)
    add_live_argument(fl, "the companion serves it: its camera, CNN and estimate beside the truth")
    add_episode_arguments(
        fl,
        episodes=20,
        seed=EVAL_SEED,
        episodes_help="episodes (default 20)",
        seed_help=f"scenario seed (default {EVAL_SEED}, the evaluation seed, disjoint from "
        "training)",
    )
    fl.add_argument("--realtime", action="store_true", help="real time instead of lockstep")
    link = fl.add_argument_group(
        "impaired link (--realtime only; over the scenario's [link]; seeded by --seed)"
    )
    for flag in _LINK_FLAGS:
        link.add_argument(flag.flag, type=float, default=None, metavar=flag.metavar, help=flag.help)
        if flag.deprecated:
            add_deprecated_alias(link, flag.deprecated, flag.flag, flag.dest, type=float)
    fl.add_argument(
        "--instances",
        type=int,
        default=1,
        help="SITL + companion pairs side by side, each on its own ports (default 1)",
    )
    fl.add_argument(
        "--out",
        type=Path,
        default=None,
        help="run folder for both processes' logs (default: a new temporary folder)",
    )
    fl.add_argument(
        "--scene",
        action="store_true",
        help="after the run, write the live view's picture into its logs (as visland log "
        "scene), so each opens in Foxglove like a live flight (needs 'visland[live]')",
    )
    fl.add_argument("--json", action="store_true", help="print one JSON object")
    add_backend_arguments(fl)
    fl.set_defaults(func=cmd_fly)


def register_sim(sub: argparse._SubParsersAction) -> None:
    """Add ``demo``, ``readme``, ``sitl``, ``companion`` and ``fly`` to the ``visland``
    subcommands."""
    from companion.config import add_arguments as add_companion_arguments
    from sitl_sim.mavlink.config import add_sitl_arguments

    _register_demo(sub)
    _register_readme(sub)
    st = sub.add_parser(
        "sitl", help="the MAVLink 2 SITL: a PX4-like autopilot over UDP (lockstep or real time)"
    )
    add_sitl_arguments(st, seed=EVAL_SEED)
    st.set_defaults(func=_cmd_sitl)
    cp = sub.add_parser(
        "companion",
        help="the companion process: flies a policy through a PX4/ArduPilot autopilot",
    )
    add_companion_arguments(cp)
    cp.set_defaults(func=_cmd_companion)
    _register_install_service(cp)
    _register_fly(sub)
    _register_soak(sub)
