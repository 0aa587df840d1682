"""What Ray prints while training: every line reaches the run's Ray log; the terminal gets those that matter."""

from __future__ import annotations

import importlib
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
from ray._private.worker import global_worker_stdstream_dispatcher as dispatcher

from endoflow.config import RayConfig
from endoflow.ray_runtime import (
    PREEMPTION_WATCHER_ENV,
    RAY_PRINT_HANDLER,
    ray_train_settings,
    without_token_auth_notice,
    worker_logs_to,
)
from endoflow.ray_worker_setup import QUIETED_RAY_TRAIN_LOGGERS, ray_train_context_logger_name

PREEMPTION_LINE = ("[2026-11-23 10:16:45,165 E 15215 15243] core_worker.cc:2465: Actor with class name: "
                   "'PreemptionWatcher' and ID: '82f8' has constructor arguments in the object store and "
                   "max_restarts > 0.")


@pytest.fixture
def printed() -> list[dict]:
    """What Ray's own printer would print, registered as Ray registers it."""
    seen: list[dict] = []
    dispatcher.add_handler(RAY_PRINT_HANDLER, seen.append)
    yield seen
    dispatcher.remove_handler(RAY_PRINT_HANDLER)


def test_every_line_goes_to_the_log_and_only_unactionable_ones_leave_the_terminal(printed, tmp_path: Path):
    log = tmp_path / "ray.log"
    progress = {"pid": 7, "actor_name": "RayTrainWorker", "is_err": False,
                "lines": ["[train] epoch 1/2 step 1/1 loss 0.27"]}
    controller = {"pid": 8, "actor_name": "TrainController", "is_err": True,
                  "lines": [PREEMPTION_LINE, "Traceback (most recent call last):"]}
    with worker_logs_to(log):
        dispatcher.emit(progress)
        dispatcher.emit(controller)
        dispatcher.emit({**controller, "lines": [PREEMPTION_LINE]})
    dispatcher.emit(controller)  # after: Ray's printer is back, unchanged

    assert [d["lines"] for d in printed] == [progress["lines"], ["Traceback (most recent call last):"],
                                              controller["lines"]]
    assert log.read_text().splitlines() == [
        "(RayTrainWorker pid=7) [train] epoch 1/2 step 1/1 loss 0.27",
        f"(TrainController pid=8, stderr) {PREEMPTION_LINE}",
        "(TrainController pid=8, stderr) Traceback (most recent call last):",
        f"(TrainController pid=8, stderr) {PREEMPTION_LINE}"]


def test_the_token_auth_enabled_notice_is_dropped_and_the_disabled_warning_kept(caplog):
    from ray._private.authentication import authentication_token_setup as auth

    with caplog.at_level(logging.WARNING, logger=auth.logger.name), without_token_auth_notice():
        auth._warn_token_auth_enabled()
        auth._warn_token_auth_disabled()
    assert [r.getMessage()[:45] for r in caplog.records] == ["Token authentication is disabled for this Ray"]


def test_colour_codes_reach_only_a_terminal(monkeypatch, tmp_path: Path) -> None:
    coloured = {"pid": 7, "actor_name": "RayTrainWorker", "is_err": True,
                "lines": ["\x1b[33m(raylet)\x1b[0m \x1b[1mWARNING\x1b[0m: 1 worker restarted"]}
    printed: list[tuple[list[str], str | None]] = []

    def ray_printer(data: dict) -> None:  # Ray's printer colours the prefix unless RAY_COLOR_PREFIX is "0"
        printed.append((data["lines"], os.environ.get("RAY_COLOR_PREFIX")))

    monkeypatch.delenv("RAY_COLOR_PREFIX", raising=False)
    dispatcher.add_handler(RAY_PRINT_HANDLER, ray_printer)
    try:
        with worker_logs_to(tmp_path / "ray.log"):
            dispatcher.emit(coloured)  # stderr is pytest's capture: not a terminal
            monkeypatch.setattr("endoflow.ray_runtime.is_terminal", lambda stream: True)
            dispatcher.emit(coloured)
    finally:
        dispatcher.remove_handler(RAY_PRINT_HANDLER)

    assert printed == [(["(raylet) WARNING: 1 worker restarted"], "0"), (coloured["lines"], None)]
    assert "RAY_COLOR_PREFIX" not in os.environ
    assert (tmp_path / "ray.log").read_text().splitlines() == [
        "(RayTrainWorker pid=7, stderr) (raylet) WARNING: 1 worker restarted"] * 2


def test_the_quieted_loggers_are_the_ones_ray_train_logs_with():
    """The worker setup names Ray Train's loggers without importing Ray Train: each name must be the logger its
    module logs with, or the lines come back after a Ray upgrade."""
    context = importlib.import_module("ray.train.v2._internal.execution.context")
    assert logging.getLogger(ray_train_context_logger_name()) is context.logger
    for name in QUIETED_RAY_TRAIN_LOGGERS:
        assert logging.getLogger(name) is importlib.import_module(name).logger, name


def test_quieting_ray_trains_loggers_imports_neither_ray_train_nor_endoflows_config():
    """Every worker process of a job runs the setup: Ray Train (with Ray Data, pandas and pyarrow) would cost each
    about 1.7 s of CPU on 2 cores, endoflow's config (pydantic) 0.3 s, and most workers never train."""
    script = ("import sys, logging\n"
              "from endoflow.ray_worker_setup import quiet_ray_train_loggers, ray_train_context_logger_name\n"
              "quiet_ray_train_loggers()\n"
              "assert logging.getLogger(ray_train_context_logger_name()).level == logging.WARNING\n"
              "heavy = ('ray.train', 'ray.data', 'pandas', 'pydantic', 'endoflow.config')\n"
              "print(sorted(m for m in sys.modules if m.startswith(heavy)))\n")
    assert printed_by_a_fresh_interpreter(script) == ["[]"]


def printed_by_a_fresh_interpreter(script: str) -> list[str]:
    """The lines ``script`` prints, run by a new Python process (which must succeed): nothing it imports or
    configures stays in the test process."""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-3000:]
    return run.stdout.splitlines()


def test_the_quieted_loggers_stay_quiet_after_ray_train_configures_its_logging():
    """Ray Train runs ``logging.config.dictConfig`` on ``ray.train`` in its controller after the worker setup, which
    resets the levels of the loggers below it: the autoscaling coordinator's timeout traceback reached the paper
    dry run's output under load. Here the same configuration, in a fresh interpreter."""
    script = ("import logging, logging.config\n"
              "from endoflow.ray_worker_setup import QUIETED_RAY_TRAIN_LOGGERS, quiet_ray_train_loggers\n"
              "quiet_ray_train_loggers()\n"
              "quiet_ray_train_loggers()  # a second setup adds nothing\n"
              "logging.config.dictConfig({'version': 1, 'disable_existing_loggers': False,\n"
              "    'handlers': {'out': {'class': 'logging.StreamHandler', 'stream': 'ext://sys.stdout'}},\n"
              "    'loggers': {'ray.train': {'level': 'INFO', 'handlers': ['out'], 'propagate': False}}})\n"
              "for name in QUIETED_RAY_TRAIN_LOGGERS:\n"
              "    logger = logging.getLogger(name)\n"
              "    assert logger.level == logging.NOTSET and len(logger.filters) == 1  # level reset, filter kept\n"
              "    logger.warning('quieted %s', name)\n"
              "    logger.error('kept %s', name)\n"
              "logging.getLogger('ray.train.v2.other').warning('kept other')\n")
    kept = [f"kept {name}" for name in QUIETED_RAY_TRAIN_LOGGERS] + ["kept other"]
    assert printed_by_a_fresh_interpreter(script) == kept


def test_a_local_ray_trains_without_a_preemption_watcher_a_cluster_and_a_users_setting_keep_theirs(monkeypatch):
    """Ray Train's controller reads the switch from the driver's environment when ``fit`` starts: one machine is
    never drained like a cloud's spot instance, so a local Ray has nothing to watch (tests/test_ray.py finds the
    watcher's line absent from a local training's Ray log)."""
    monkeypatch.delenv(PREEMPTION_WATCHER_ENV, raising=False)
    with ray_train_settings(RayConfig()):
        assert os.environ[PREEMPTION_WATCHER_ENV] == "0"
    assert PREEMPTION_WATCHER_ENV not in os.environ
    with ray_train_settings(RayConfig(address="10.0.0.1:6379")):
        assert PREEMPTION_WATCHER_ENV not in os.environ
    monkeypatch.setenv(PREEMPTION_WATCHER_ENV, "1")
    with ray_train_settings(RayConfig()):
        assert os.environ[PREEMPTION_WATCHER_ENV] == "1"
