"""The Ray backend (``--ray ADDRESS``): a command's episodes as Ray tasks on a cluster.

Each in-process episode, each log to relabel and each SITL + companion run is one Ray task,
placed by resources (1 CPU; a SITL + companion pair asks for 2, and picks its UDP ports on the
node it runs on). A worker process keeps its env and policy between tasks of the same spec, as
a local worker does. What a task needs travels with it: a checkpoint as bytes (cached on each
node by sha256), a scenario file as a checked scenario. Flight logs come back to the driver's
folder with the names and bytes a local run writes — as Ray objects, or through ``shared_dir``
(a folder every node mounts at the same path) — and are renamed into place only when complete.

Retries: a task that fails (a lost node or worker, or an error in the episode) is submitted
once more by the driver, which says which were retried (Ray's own ``max_retries`` is 0 so the
count is exact and the run can name them); work that fails twice is a :class:`BackendError`
naming it, raised after everything else has finished, so nothing already flown is lost and a
rerun resumes. Every node must run the same visland commit as the driver (checked per task).
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import socket
import sys
import tempfile
import uuid
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from companion.files import sha256_file
from training.exec.backend import Backend, BackendError
from training.provenance import REPO, git_commit

__all__ = ["RayBackend", "ray_available"]

_INSTALL = "the Ray backend needs Ray: pip install 'visland[ray]' (ray 2.60.0)"


def ray_available() -> bool:
    """Whether Ray is installed (without importing it: see :class:`RayBackend` on loopback)."""
    return importlib.util.find_spec("ray") is not None


def _ray():
    try:
        import ray
    except ImportError:
        raise BackendError(_INSTALL) from None
    return ray


# --------------------------------------------------------------------------- on the nodes

_NODE: dict[str, Any] = {}


def _node_dir() -> Path:
    """This worker process's scratch folder (node-local)."""
    if "dir" not in _NODE:
        _NODE["dir"] = Path(tempfile.mkdtemp(prefix="visland_ray_"))
    return _NODE["dir"]


def _check_commit(driver: str) -> None:
    mine = _NODE.get("commit")
    if mine is None:
        mine = _NODE["commit"] = git_commit()
    if mine != driver:
        raise BackendError(
            f"node {socket.gethostname()} runs visland {mine}, the driver {driver}: every node "
            "must run the driver's commit (the same code flies the same episodes)"
        )


def _node_policy(sha: str | None, data: bytes | None) -> str | None:
    """The node's copy of a checkpoint (by sha256; written once per node)."""
    if sha is None or data is None:
        return None
    folder = Path(tempfile.gettempdir()) / "visland_ray_policies"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{sha}.pt"
    if not path.exists():
        tmp = folder / f"{sha}.{os.getpid()}.part"
        tmp.write_bytes(data)
        tmp.replace(path)
    return str(path)


def _take(path: Path, shared: Path | None) -> bytes | str:
    """A finished file handed to the driver: its bytes (removed here), or its path in the
    shared folder."""
    if shared is not None:
        return str(path)
    data = path.read_bytes()
    path.unlink()
    return data


def _episode_task(spec, index, policy_sha, policy_data, commit, shared):
    from training.exec.rollout import fly_in_this_process

    _check_commit(commit)
    log_dir = None
    if spec.log_dir is not None:
        log_dir = str(Path(shared) if shared else _node_dir() / "logs")
    local = replace(spec, log_dir=log_dir)
    outcome = fly_in_this_process(local, index, _node_policy(policy_sha, policy_data))
    log = None
    if outcome.log_path is not None:
        log = _take(Path(outcome.log_path), Path(shared) if shared else None)
    return outcome, log


def _relabel_task(name, log, commit, shared):
    from expert.relabel import _safe_relabel

    _check_commit(commit)
    work = _node_dir() / "relabel"
    work.mkdir(parents=True, exist_ok=True)
    if isinstance(log, bytes):
        src = work / name
        src.write_bytes(log)
    else:
        src = Path(log)
    out = Path(shared) / "labels" if shared else work / "labels"
    try:
        report = _safe_relabel((str(src), str(out)))
    finally:
        if isinstance(log, bytes):
            src.unlink(missing_ok=True)
    labels = None
    if report.labels is not None:
        labels = _take(Path(report.labels), Path(shared) if shared else None)
    return report, str(src), labels


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _fly_task(cfg, first, count, policy_sha, policy_data, scenario, commit):
    from training.exec.fly import fly_run

    _check_commit(commit)
    policy = _node_policy(policy_sha, policy_data) or cfg.policy
    work = Path(tempfile.mkdtemp(prefix=f"fly{first}_", dir=_node_dir()))
    try:
        if scenario is not None:
            name, data = scenario
            where = REPO / name
            if not (where.is_file() and where.read_bytes() == data):
                where = work / Path(name).name
                where.write_bytes(data)
            cfg = replace(cfg, scenario=str(where))
        report = fly_run(replace(cfg, policy=policy), first, count, work / "out", work / "sitl")
        ep = work / "out" / f"ep{first:04d}"
        return report, _files(ep), _files(work / "sitl")
    finally:
        shutil.rmtree(work, ignore_errors=True)


# --------------------------------------------------------------------------- the driver


def _place(data: bytes | str, dst: Path) -> None:
    """Write (or move, from the shared folder) a finished file to ``dst``, atomically."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(dst.name + ".part")
    if isinstance(data, bytes):
        tmp.write_bytes(data)
    else:
        shutil.move(data, tmp)
    tmp.replace(dst)


def _probe(address: str, timeout_s: float = 5.0) -> None:
    """A TCP connect to ``HOST:PORT`` (or ``ray://HOST:PORT``) first: Ray itself retries an
    unreachable head for minutes before it gives up."""
    if address == "auto":
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise BackendError(
            f"--ray {address}: cannot reach {host}:{port} ({exc.strerror or exc}); is the head "
            f"node started (`ray start --head --port {port}`) and reachable from here?"
        ) from None


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__


class RayBackend(Backend):
    """A Ray cluster: ``address`` is ``auto``, ``local`` (a Ray instance started here, with its
    own temp folder, stopped by :meth:`close`), ``ray://HOST:PORT`` or ``HOST:PORT``."""

    name = "ray"

    def __init__(
        self,
        address: str,
        shared_dir: str | Path | None = None,
        say: Callable[[str], None] | None = None,
        num_cpus: int | None = None,
    ) -> None:
        super().__init__()
        if address == "local" and "ray" not in sys.modules:
            # a local instance is one node: Ray then binds and registers 127.0.0.1 instead of
            # the host's network address, so nothing outside this host can reach it (Ray reads
            # this when it is imported)
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        if address == "local":
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing leaves this host
        ray = _ray()
        self._say = say or (lambda msg: print(msg, file=sys.stderr, flush=True))
        self.address = address
        self.shared = None
        if shared_dir is not None:
            self.shared = Path(shared_dir).resolve() / f"visland-{uuid.uuid4().hex[:12]}"
            try:
                self.shared.mkdir(parents=True)
            except OSError as exc:
                raise BackendError(
                    f"--shared-dir {shared_dir}: cannot create a folder: {exc}"
                ) from None
        self._tmp = None
        if ray.is_initialized():
            raise BackendError("Ray is already initialised in this process")
        if address == "local":
            # a short own folder: Ray's socket paths must stay under 108 characters
            self._tmp = tempfile.mkdtemp(prefix="vray_", dir="/tmp")
            ctx = ray.init(
                address="local",
                num_cpus=num_cpus or os.cpu_count() or 1,
                _temp_dir=self._tmp,
                include_dashboard=False,
                logging_level="WARNING",
            )
        else:
            _probe(address)
            try:
                ctx = ray.init(address=address, logging_level="WARNING")
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise BackendError(f"--ray {address}: cannot connect: {_short(exc)}") from None
        self.commit = git_commit()
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        self.cpus = int(ray.cluster_resources().get("CPU", 1))
        dashboard = getattr(ctx, "dashboard_url", None)
        self._say(
            f"ray: {address}: {len(nodes)} node(s), {self.cpus} CPUs"
            + (f"; dashboard http://{dashboard}" if dashboard else "")
        )
        self._ray = ray
        self._episode = ray.remote(_episode_task).options(num_cpus=1, max_retries=0)
        self._relabel = ray.remote(_relabel_task).options(num_cpus=1, max_retries=0)
        self._fly = ray.remote(_fly_task).options(num_cpus=2, max_retries=0)
        self._policies: dict[str, tuple[str, Any]] = {}

    @property
    def slots(self) -> int:
        return self.cpus

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "address": self.address}

    def close(self) -> None:
        if self._ray is not None and self._ray.is_initialized():
            self._ray.shutdown()
        self._ray = None
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None
        if self.shared is not None:
            shutil.rmtree(self.shared, ignore_errors=True)

    # ------------------------------------------------------------------ helpers

    def _policy(self, policy: str) -> tuple[str | None, Any]:
        """(sha256, object ref of the bytes) of a checkpoint path; (None, None) for the
        built-in pilots, which every node has."""
        if policy in ("expert", "cascade") or not Path(policy).is_file():
            return None, None
        if policy not in self._policies:
            sha = sha256_file(policy)
            self._policies[policy] = (sha, self._ray.put(Path(policy).read_bytes()))
        return self._policies[policy]

    def _map(
        self,
        items: list[Any],
        submit: Callable[[Any], Any],
        what: Callable[[Any], str],
        done: Callable[[Any, Any], None],
        cpus_each: int = 1,
    ) -> list[tuple[Any, str]]:
        """Run ``submit(item)`` tasks with a bounded number in flight, ``done(item, value)`` as
        each finishes; a failed task is submitted once more (and named in ``retried``).
        Returns (item, why) for each item that failed twice."""
        ray = self._ray
        window = max(2, 2 * self.cpus // cpus_each)
        queue = deque(items)
        pending: dict[Any, Any] = {}
        tries: dict[str, int] = {}
        failed: list[tuple[Any, str]] = []
        try:
            while queue or pending:
                while queue and len(pending) < window:
                    item = queue.popleft()
                    pending[submit(item)] = item
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    item = pending.pop(ref)
                    try:
                        value = ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        name = what(item)
                        tries[name] = tries.get(name, 0) + 1
                        if tries[name] == 1:
                            self.retried.append(name)
                            self._say(f"ray: {name} failed ({_short(exc)}); trying again")
                            queue.appendleft(item)
                        else:
                            failed.append((item, f"{name}: failed twice: {_short(exc)}"))
                        continue
                    done(item, value)
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        return failed

    # ------------------------------------------------------------------ the work

    def episodes(self, spec, indices, on_done=None):
        from sitl_sim.config import load_sim, load_vehicle
        from sitl_sim.scenario import load_scenario
        from training.exec.rollout import log_name

        # what a node may not have travels as checked configs (the same values, the same
        # ``source`` names in the logs)
        portable = replace(
            spec,
            scenario=load_scenario(spec.scenario)
            if isinstance(spec.scenario, str | Path)
            else spec.scenario,
            vehicle=load_vehicle(spec.vehicle) if isinstance(spec.vehicle, str) else spec.vehicle,
            sim=load_sim(spec.sim) if isinstance(spec.sim, str) else spec.sim,
        )
        sha, data = self._policy(spec.policy)
        shared = str(self.shared / "logs") if self.shared else None
        outcomes = []

        def done(index, value):
            outcome, log = value
            if log is not None:
                dst = Path(spec.log_dir) / log_name(spec.seed, index)
                _place(log, dst)
                outcome = replace(outcome, log_path=str(dst))
            outcomes.append(outcome)
            if on_done is not None:
                on_done(outcome)

        failed = self._map(
            list(indices),
            lambda i: self._episode.remote(portable, i, sha, data, self.commit, shared),
            lambda i: f"episode {i} of seed {spec.seed}",
            done,
        )
        if failed:
            raise BackendError(
                f"{len(failed)} of {len(indices)} episodes failed (the {len(outcomes)} that "
                "finished are kept; a rerun of a logging command resumes):\n"
                + "\n".join(why for _, why in failed)
            )
        return sorted(outcomes, key=lambda o: o.episode_index)

    def relabel(self, logs, out_dir, on_done=None):
        from expert.relabel import RelabelReport

        out_dir = Path(out_dir)
        reports: dict[int, RelabelReport] = {}
        inbox = self.shared / "in" if self.shared else None
        shared = str(self.shared) if self.shared else None

        def submit(k):
            src = Path(logs[k])
            if inbox is not None:
                inbox.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, inbox / src.name)
                log = str(inbox / src.name)
            else:
                log = self._ray.put(src.read_bytes())
            return self._relabel.remote(src.name, log, self.commit, shared)

        def done(k, value):
            report, node_src, labels = value
            src = str(logs[k])
            dst = None
            if labels is not None:
                dst = out_dir / Path(report.labels).name
                _place(labels, dst)
            error = report.error.replace(node_src, src) if report.error else None
            reports[k] = replace(report, log=src, labels=str(dst) if dst else None, error=error)
            if inbox is not None:
                (inbox / Path(src).name).unlink(missing_ok=True)
            if on_done is not None:
                on_done(reports[k])

        failed = self._map(list(range(len(logs))), submit, lambda k: f"relabel {logs[k]}", done)
        for k, why in failed:  # as the local backend: a log that cannot be done is reported
            reports[k] = RelabelReport(str(logs[k]), None, 0, False, why)
        return [reports[k] for k in range(len(logs))]

    def fly_runs(self, cfg, runs, out, sitl_dir, on_done=None):
        sha, data = self._policy(cfg.policy)
        scenario = None
        if cfg.scenario is not None:
            path = Path(cfg.scenario)
            where = path if path.is_absolute() else REPO / path
            name = str(path) if not path.is_absolute() else path.name
            try:
                scenario = (name, where.read_bytes())
            except OSError as exc:
                raise BackendError(f"scenario {cfg.scenario}: cannot read: {exc}") from None
        reports = []

        def done(run, value):
            first, n = run
            report, ep_files, sitl_files = value
            ep = Path(out) / f"ep{first:04d}"
            for rel, blob in ep_files.items():
                _place(blob, ep / rel)
            for rel, blob in sitl_files.items():
                _place(blob, Path(sitl_dir) / rel)
            rows = tuple(
                replace(row, log=str(Path(sitl_dir) / Path(row.log).name))
                for row in report.per_episode
            )
            reports.append(replace(report, out=str(ep), per_episode=rows))
            if on_done is not None:
                on_done(n)

        failed = self._map(
            list(runs),
            lambda r: self._fly.remote(cfg, r[0], r[1], sha, data, scenario, self.commit),
            lambda r: f"episodes {r[0]}..{r[0] + r[1] - 1}",
            done,
            cpus_each=2,
        )
        return reports, [why for _, why in failed]
