"""The one home of connecting to Ray, for training (``endoflow.training``) and preprocessing (``endoflow.data``).

It imports only ``endoflow.config`` and the package's ``__version__`` (and Ray), so every layer that runs work on
Ray can use it.

A local Ray (``ray.address`` null) listens on loopback only: GCS, raylet, object manager and workers (and
the gloo connections of DDP, which follow the node address). Ray binds its servers to the node's address, and
for a local instance it takes the machine's routable one (it even rewrites ``_node_ip_address="127.0.0.1"``
to it), except where it treats multi-node Ray as off (Windows and macOS: ``ray_constants.ENABLE_RAY_CLUSTER``).
:func:`connect_ray` turns that off while it starts the local instance, so Ray gives every process it spawns
127.0.0.1 as the node address; ``tests/test_ray_cluster.py`` checks what listens. One socket stays open to
every interface while training runs: the rendezvous store (``TCPStore``) that torch opens in rank 0 binds all
interfaces whatever address it is given, and Ray Train offers no way to hand it a bound socket.

Every job, local or on a cluster, ships this tree's ``endoflow`` package to its workers through the job's
``runtime_env`` (``py_modules``), then runs one small task on every live node that reports the endoflow it
imports: its version and a SHA-256 of its source files. A node that differs from the driver stops the start
with :class:`ClusterMismatchError` naming it. Without the shipping, a local Ray's workers import the installed
endoflow: a queued DVC experiment, run in a copy of the project, trained with the workspace's loop, edited since
(seen: a worker failed on a params field the copy did not have). On a cluster a node differs when the driver's
working directory also exists there with another endoflow checkout in it: Ray puts that directory first on its
workers' ``sys.path``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, TextIO

import endoflow
from endoflow.config import ConfigError, RayConfig
from endoflow.progress import environment_default

# How long every node gets to start a worker (with the shipped package) and report its endoflow.
NODE_CHECK_TIMEOUT_S = 120.0
# Lines Ray prints about itself that nobody can act on; they still reach the run's Ray log (worker_logs_to).
# Ray Train's controller logs an internal actor's restart policy at ERROR level on every start
# (https://github.com/ray-project/ray/issues/53727); on a cluster, as a local Ray runs no such actor
# (ray_train_settings).
UNACTIONABLE_RAY_LINES = (re.compile(r"core_worker\.cc:\d+: Actor with class name: 'PreemptionWatcher'"),)
# Ray's notice, at every local start, that it turned on token authentication (what we want: nothing to do);
# the notice that authentication is *off*, when joining a cluster without it, still shows.
TOKEN_AUTH_ENABLED_NOTICE = "Token authentication is enabled for this Ray cluster"
# the name under which Ray's driver prints the lines its workers and own processes stream to it
RAY_PRINT_HANDLER = "ray_print_logs"
# a terminal's colour and cursor codes (ESC [ ... letter): Ray colours the "(worker pid=...)" prefixes it prints
# and some of the lines it streams; a file or a pipe gets them as litter
ANSI_ESCAPE = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]")
# Ray prints the prefixes uncoloured with this set to "0" (read at every line)
RAY_COLOR_PREFIX_ENV = "RAY_COLOR_PREFIX"
# Ray Train's switch for its preemption watcher, read from the driver's environment when a training starts
PREEMPTION_WATCHER_ENV = "RAY_TRAIN_ENABLE_PREEMPTION_WATCHER"


class ClusterMismatchError(ConfigError):
    """A node of the Ray cluster at ``ray.address`` imports another endoflow than the driver; rerunning does
    not help until every node has the driver's."""


@dataclass(frozen=True)
class EndoflowBuild:
    """The endoflow a process imports: version, SHA-256 of its ``*.py`` files (by relative path), and folder."""

    version: str
    sha256: str
    location: str

    def same_code(self, other: EndoflowBuild) -> bool:
        return (self.version, self.sha256) == (other.version, other.sha256)

    def __str__(self) -> str:
        return f"endoflow {self.version} (sources sha256 {self.sha256[:16]}) from {self.location}"


def connect_ray(cfg: RayConfig) -> bool:
    """Join ``ray.address`` or start a small local Ray on loopback; returns whether this call connected.

    Joining checks that every node imports the driver's endoflow (see the module docstring).

    Raises:
        ClusterMismatchError: naming each node whose endoflow differs; the connection is closed again.
    """
    import ray

    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if cfg.address:
        with without_token_auth_notice():
            ray.init(address=cfg.address, log_to_driver=True, logging_level=logging.WARNING,
                     runtime_env=shipped_runtime_env())
    else:
        # "local": a new instance even where `ray start` left one running
        with multi_node_ray_off(), without_token_auth_notice():
            ray.init(address="local", num_cpus=cfg.num_cpus or os.cpu_count(), include_dashboard=False,
                     object_store_memory=cfg.object_store_mb * 2**20, log_to_driver=True,
                     logging_level=logging.WARNING, runtime_env=shipped_runtime_env())
    try:
        check_same_endoflow_on_every_node(endoflow_build())
    except BaseException:
        ray.shutdown()
        raise
    if cfg.address:
        # Ray's own "Connecting to existing Ray cluster" line is INFO, below the level set above
        nodes = [node for node in ray.nodes() if node.get("Alive")]
        print(f"[ray] joined the cluster at {cfg.address}: {len(nodes)} nodes, "
              f"{ray.cluster_resources().get('CPU', 0):g} CPUs", file=sys.stderr, flush=True)
    return True


@contextmanager
def ray_train_settings(cfg: RayConfig) -> Iterator[None]:
    """Within (around Ray Train's ``fit``): on a local Ray, no preemption watcher. It polls for nodes being drained
    (a cloud's spot instance about to go), which one machine never is; it costs an actor per training (2.6 s of CPU
    to start on 2 cores) and logs an unactionable error at every start (:data:`UNACTIONABLE_RAY_LINES`). A cluster
    (``ray.address``) keeps it; a user's own setting stays."""
    if cfg.address:
        yield
        return
    with environment_default(PREEMPTION_WATCHER_ENV, "0"):
        yield


@contextmanager
def without_token_auth_notice() -> Iterator[None]:
    """Within: Ray's "token authentication is enabled" notice is not printed (other auth warnings are). Ray
    versions without token authentication have neither the notice nor the module."""
    try:
        from ray._private.authentication import authentication_token_setup
    except ImportError:
        yield
        return

    def keep(record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith(TOKEN_AUTH_ENABLED_NOTICE)

    authentication_token_setup.logger.addFilter(keep)
    try:
        yield
    finally:
        authentication_token_setup.logger.removeFilter(keep)


@contextmanager
def worker_logs_to(path: str | Path) -> Iterator[None]:
    """Within (Ray connected, printing what its processes stream to the driver): every such line is also
    appended to ``path``, and the terminal gets all but :data:`UNACTIONABLE_RAY_LINES`. Colour codes reach only
    a terminal: the file, and standard output or error when it is a file or a pipe, get the lines without them."""
    from ray._private.worker import global_worker_stdstream_dispatcher as dispatcher

    printer = dict(dispatcher.handlers).get(RAY_PRINT_HANDLER)
    with open(path, "a", encoding="utf-8") as log:
        def route(data: dict[str, Any]) -> None:
            write_ray_lines(log, data)
            shown = [line for line in data["lines"]
                     if not any(pattern.search(line) for pattern in UNACTIONABLE_RAY_LINES)]
            if printer is None or not shown:
                return
            if is_terminal(sys.stderr if data.get("is_err") else sys.stdout):
                printer({**data, "lines": shown})
                return
            with uncoloured_prefixes():
                printer({**data, "lines": [without_colours(line) for line in shown]})

        dispatcher.remove_handler(RAY_PRINT_HANDLER)
        dispatcher.add_handler(RAY_PRINT_HANDLER, route)
        try:
            yield
        finally:
            dispatcher.remove_handler(RAY_PRINT_HANDLER)
            if printer is not None:
                dispatcher.add_handler(RAY_PRINT_HANDLER, printer)


def write_ray_lines(log: TextIO, data: dict[str, Any]) -> None:
    """Append streamed lines to ``log``, each after the process it came from, as Ray prints them (without
    colour codes)."""
    source = data.get("actor_name") or data.get("task_name") or ""
    prefix = f"({source} pid={data.get('pid')}{', stderr' if data.get('is_err') else ''}) "
    log.writelines(prefix + without_colours(line) + "\n" for line in data["lines"])
    log.flush()


def without_colours(line: str) -> str:
    """``line`` without terminal colour codes (:data:`ANSI_ESCAPE`)."""
    return ANSI_ESCAPE.sub("", line)


def is_terminal(stream: TextIO) -> bool:
    """Whether ``stream`` writes to a terminal (not a file, a pipe, or a closed or captured stream)."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


@contextmanager
def uncoloured_prefixes() -> Iterator[None]:
    """Within: Ray prints its ``(worker pid=...)`` prefixes without colour, unless the user chose otherwise in
    :data:`RAY_COLOR_PREFIX_ENV`. Ray's printer runs in the driver's one log thread, which alone reads it."""
    with environment_default(RAY_COLOR_PREFIX_ENV, "0"):
        yield


def shipped_runtime_env() -> dict[str, Any]:
    """The job's ``runtime_env``: this tree's endoflow package on every node (Ray uploads it once per content,
    without bytecode caches), and the setup every worker process runs first (``endoflow/ray_worker_setup.py``)."""
    return {"py_modules": [str(package_folder())], "excludes": ["__pycache__"],
            "worker_process_setup_hook": "endoflow.ray_worker_setup.set_up_worker"}


@contextmanager
def multi_node_ray_off() -> Iterator[None]:
    """Within: Ray takes 127.0.0.1 as this machine's node address, as on Windows and macOS (a local Ray
    started inside gives it to every process it spawns). Ray reads the switch when it needs the address."""
    from ray._private import ray_constants

    before = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = before


# ------------------------------------------------------------------------------ the same endoflow everywhere
def package_folder() -> Path:
    """The folder of the endoflow package this process imports."""
    return Path(endoflow.__file__).resolve().parent


def endoflow_build() -> EndoflowBuild:
    """The endoflow this process imports (runs on the driver and, as a Ray task, on every node)."""
    folder = package_folder()
    digest = hashlib.sha256()
    for path in sorted(folder.rglob("*.py"), key=lambda p: p.relative_to(folder).as_posix()):
        digest.update(path.relative_to(folder).as_posix().encode() + b"\0")
        digest.update(hashlib.sha256(path.read_bytes()).digest())
    return EndoflowBuild(endoflow.__version__, digest.hexdigest(), str(folder))


def check_same_endoflow_on_every_node(expected: EndoflowBuild) -> None:
    """Raise :class:`ClusterMismatchError` naming every live node of the connected cluster whose workers
    import another endoflow than ``expected`` (or none at all)."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    report = ray.remote(num_cpus=0, max_retries=0)(endoflow_build)
    nodes = [node for node in ray.nodes() if node["Alive"]]
    pending = [report.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False))
               .remote() for node in nodes]
    problems = []
    for node, ref in zip(nodes, pending):
        name = f"node {node['NodeID'][:12]} ({node['NodeManagerAddress']})"
        try:
            found = ray.get(ref, timeout=NODE_CHECK_TIMEOUT_S)
        except (ray.exceptions.RayError, ImportError) as exc:
            problems.append(f"{name}: cannot report its endoflow ({type(exc).__name__}: {exc})")
            continue
        if not found.same_code(expected):
            problems.append(f"{name} imports {found}")
    if problems:
        raise ClusterMismatchError(
            f"the Ray workers import another endoflow than this driver's {expected}: "
            + "; ".join(problems)
            + ". Every node must import the driver's endoflow: its workers get this tree's package through "
              "runtime_env py_modules, unless the driver's working directory holds another endoflow on that node "
              "(update that checkout, or start the stage from a folder that does not exist there)")
