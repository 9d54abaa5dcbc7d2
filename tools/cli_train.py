"""`visland train STAGE` and `visland pipeline`: thin shells over training.pipeline."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tools.cli_args import config_from_args

__all__ = ["register_training"]


def _profile(args: argparse.Namespace):
    """The named profile, with ``--rollouts`` when given."""
    from dataclasses import replace

    from training.profiles import PROFILES

    prof = PROFILES[args.profile]
    return replace(prof, rollouts=args.rollouts) if args.rollouts else prof


def _cmd_pipeline(args: argparse.Namespace) -> int:
    from training.exec.choose import backend_from_args
    from training.pipeline import run_pipeline

    stages = tuple(args.stages.split(",")) if args.stages else None
    prof = _profile(args)
    with backend_from_args(args, prof.workers) as backend:
        records = run_pipeline(
            args.out,
            prof,
            args.scenario,
            stages=stages,
            progress=not args.no_progress,
            backend=backend,
            start_from=args.start_from,
            pad=args.pad,
        )
    metrics = Path(args.out) / "metrics.json"
    if args.json:
        print(json.dumps(records, indent=2, default=str))
    elif args.pad is not None:
        for stage, rec in records.items():
            print(f"{stage:>11}: done  {rec.get('checkpoint') or rec.get('metrics') or ''}")
        if "eval" in records:
            _print_pad_suite(Path(args.out))
    else:
        for stage, rec in records.items():
            ckpt = rec.get("checkpoint") or rec.get("metrics") or ""
            print(f"{stage:>11}: done  {ckpt}")
        if metrics.exists() and "eval" in records:
            rows = json.loads(metrics.read_text())["rows"]
            print(f"\n{'row':>8} {'mean m':>8} {'max m':>8} {'td m/s':>8} {'success':>8}")
            for name, r in rows.items():
                print(
                    f"{name:>8} {r['landing_error_m']['mean']:>8.3f} "
                    f"{r['landing_error_m']['max']:>8.3f} "
                    f"{r['touchdown_speed_m_s']['mean']:>8.3f} "
                    f"{100 * r['success_rate']:>7.1f}%"
                )
    return 0


def _print_pad_suite(run: Path) -> None:
    """The taught model's suite beside the model it started from (``pad_metrics.json``)."""
    from training.pad_teach import PadMetrics
    from training.reports import SuiteReport

    m = PadMetrics.from_dict(json.loads((run / "pad_metrics.json").read_text()))
    ours, theirs = SuiteReport.load(m.report), SuiteReport.load(m.baseline)
    before = Path(m.source.checkpoint).name
    print(f"\npad {m.pad.name}: the taught model and {before} before, seed {m.eval_seed}")
    print(f"{'condition':>20} {'success':>8} {'mean m':>8} {'before':>8} {'mean m':>8}")
    for name, r in ours.conditions.items():
        s, b = r.summary, theirs.conditions[name].summary
        print(
            f"{name:>20} {100 * (s.success_rate or 0):>7.1f}% {s.landing_error_m.mean or 0:>8.3f}"
            f" {100 * (b.success_rate or 0):>7.1f}% {b.landing_error_m.mean or 0:>8.3f}"
        )


def _cmd_train(args: argparse.Namespace) -> int:
    from training.exec.choose import backend_from_args
    from training.pipeline import run_pipeline

    prof = _profile(args)
    with backend_from_args(args, prof.workers) as backend:
        run_pipeline(
            args.run,
            prof,
            args.scenario,
            stages=(args.stage,),
            progress=not args.no_progress,
            redo=args.stage if args.redo else None,
            backend=backend,
        )
    rec = json.loads((Path(args.run) / "stages" / f"{args.stage}.json").read_text())
    print(json.dumps(rec, indent=2) if args.json else f"{args.stage}: {rec.get('checkpoint', rec)}")
    return 0


def _cmd_ship(args: argparse.Namespace) -> int:
    from training.ship import card_file, ship

    try:
        dst = ship(args.run, args.out, args.name, tuple(args.suite_report))
    except ValueError as exc:
        print(f"visland ship: {exc}", file=sys.stderr)
        return 2
    print(f"shipped {dst} with {card_file(dst)}")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from training.report.results import ReportConfig, write_report

    res = write_report(
        config_from_args(
            ReportConfig,
            args,
            trajectories=not args.no_trajectories,
            ablations=tuple(args.ablation),
        )
    )
    print(f"wrote {res.out} and {len(res.figures)} figures")
    print(res.standing.replace("**", ""))
    for note in res.notes:
        print(note.replace("**", "").replace("`", ""))
    return 0


def register_training(sub: argparse._SubParsersAction) -> None:
    from training.exec.choose import add_backend_arguments
    from training.profiles import PROFILES, ROLLOUT_TRANSPORTS
    from training.stage_records import STAGES

    rollouts_help = (
        "how DAgger learner rollouts fly (default: the profile's, mavlink = SITL + companion "
        "processes over UDP in lockstep; inprocess = the env in worker processes); fixed per run"
    )
    pp = sub.add_parser(
        "pipeline",
        help="collect -> BC -> DAgger -> perception -> vision DAgger -> eval (resumable)",
    )
    pp.add_argument(
        "--profile",
        choices=sorted(PROFILES),
        default="quick",
        help="training profile: budgets, seeds, estimator settings (training.profiles)",
    )
    pp.add_argument("--out", type=Path, required=True, help="run folder, e.g. runs/NAME")
    pp.add_argument(
        "--scenario", default=None, help="scenario TOML (default configs/scenario.toml)"
    )
    pp.add_argument("--rollouts", choices=ROLLOUT_TRANSPORTS, default=None, help=rollouts_help)
    pp.add_argument("--stages", default=None, help=f"comma list (default all: {','.join(STAGES)})")
    pp.add_argument("--no-progress", action="store_true", help="no progress bars")
    pp.add_argument("--json", action="store_true", help="print one JSON object")
    pp.add_argument(
        "--from",
        dest="start_from",
        type=Path,
        default=None,
        metavar="RUN",
        help="a new run folder takes RUN's trained stages (collect to perception) and flies "
        "vision and eval with this profile's estimator settings: an estimator ablation "
        "without training again (the profiles may differ only in estimator settings); with "
        "--pad, RUN (a run folder or a checkpoint such as models/visland_vision.pt) gives the "
        "controller that learns the pad",
    )
    pp.add_argument(
        "--pad",
        default=None,
        metavar="PADFILE",
        help="teach this pad (configs/pads/NAME.toml or a shipped pad's NAME) to --from's "
        "controller: frames rendered with it in the profile's worlds (start altitudes scaled "
        "to its envelope) retrain the CNN, then vision and eval fly it on the pad's suite; "
        "visland ship --run OUT ships models/visland_vision_NAME.pt (training.pad_teach)",
    )
    add_backend_arguments(pp)
    pp.set_defaults(func=_cmd_pipeline)

    tr = sub.add_parser("train", help="run one training stage of a run folder (see pipeline)")
    tr.add_argument("stage", choices=STAGES)
    tr.add_argument("--run", type=Path, required=True, help="run folder")
    tr.add_argument(
        "--profile",
        choices=sorted(PROFILES),
        default="quick",
        help="training profile: budgets, seeds, estimator settings (training.profiles)",
    )
    tr.add_argument(
        "--scenario",
        default=None,
        help="scenario TOML (default configs/scenario.toml); the run's own (checked on resume)",
    )
    tr.add_argument("--rollouts", choices=ROLLOUT_TRANSPORTS, default=None, help=rollouts_help)
    tr.add_argument("--no-progress", action="store_true", help="no progress bars")
    tr.add_argument("--json", action="store_true", help="print one JSON object")
    tr.add_argument(
        "--redo",
        action="store_true",
        help="run the stage again although it has finished (the later stages' records go too)",
    )
    add_backend_arguments(tr)
    tr.set_defaults(func=_cmd_train)

    sh = sub.add_parser(
        "ship",
        help="copy a run's vision policy to models/ with its model card (a run that taught a "
        "pad: models/visland_vision_NAME.pt and .md)",
    )
    sh.add_argument("--run", type=Path, required=True, help="run folder with metrics.json")
    sh.add_argument(
        "--out", type=Path, default=Path("models"), help="folder of the shipped model and card"
    )
    sh.add_argument(
        "--name",
        default=None,
        help="ship a variant beside the default model: models/visland_vision_NAME.pt with its "
        "own card models/visland_vision_NAME.md (the default model and MODEL_CARD.md stay); "
        "a run that taught a pad ships by the pad's name unless this is given",
    )
    sh.add_argument(
        "--suite-report",
        action="append",
        default=[],
        metavar="JSON",
        help="a suite flown with the run's model (visland eval --suite ... --json > JSON), as a "
        "section of the card; repeatable",
    )
    sh.set_defaults(func=_cmd_ship)

    rp = sub.add_parser(
        "report", help="docs/results.md + figures from a run's metrics.json (paper Table 3 beside)"
    )
    rp.add_argument("--run", type=Path, required=True, help="run folder with metrics.json")
    rp.add_argument("--out", type=Path, default=Path("docs/results.md"), help="markdown to write")
    rp.add_argument(
        "--figures-dir", type=Path, default=None, help="PNG folder (default: figures/ beside --out)"
    )
    rp.add_argument(
        "--no-trajectories",
        action="store_true",
        help="skip flying the trajectory episodes (no trajectory figures)",
    )
    rp.add_argument(
        "--ablation",
        type=Path,
        action="append",
        default=[],
        help="another run of the same suite whose profile differs in one thing (e.g. "
        "runs/robust_no_hover): its suite results go beside the run's, the differing profile "
        "keys named (repeatable)",
    )
    rp.set_defaults(func=_cmd_report)
