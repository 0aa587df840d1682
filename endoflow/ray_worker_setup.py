"""What every Ray worker process of an endoflow job runs first (the job's ``worker_process_setup_hook``, set by
``endoflow/ray_runtime.py``): tasks, Ray Train's workers and Ray Train's own actors alike.

It imports nothing but Ray, which the worker has loaded already: each job starts its own worker processes, dozens
in a training, and the setup's imports are paid in every one.
"""

from __future__ import annotations

import logging
import os


def set_up_worker() -> None:
    """Ray's setup of every worker process of an endoflow job (tasks, Ray Train's workers and its own actors)."""
    address_own_cluster()
    quiet_ray_train_loggers()


def address_own_cluster() -> None:
    """Point the worker's state-API calls at its own cluster. Without an address, Ray looks for the machine's one
    running instance; where there are several (two runs side by side, or a test cluster beside a local Ray), Ray
    Train's placement-group cleaner died with "Found multiple active Ray instances", printing its traceback into
    the run's output. A user's own setting stays."""
    import ray

    os.environ.setdefault("RAY_ADDRESS", ray.get_runtime_context().gcs_address)


# Ray Train's log lines nobody can act on, by logger name: where Ray Train logs them from and the level below
# which they are dropped. Named, not imported: importing Ray Train (Ray Data, pandas, pyarrow) costs every worker
# process about 1.7 s of CPU on 2 cores, and most workers (the endoflow check, preprocessing, reconstruction)
# never use it. Loggers configured by name are the ones the modules get when they import.
QUIETED_RAY_TRAIN_LOGGERS = {
    # without the dashboard the cleaner cannot reach the state API, and warns every second; its job (cleaning up
    # after a crashed controller) is unaffected
    "ray.train.v2._internal.execution.controller.placement_group_cleaner": logging.ERROR,
    # a resource request to Ray Data's autoscaling coordinator timed out while that actor was starting on a busy
    # machine: a traceback that says itself it is safe to ignore
    "ray.train.v2._internal.execution.scaling_policy.autoscaling_coordinator_client": logging.ERROR,
}


class BelowLevelDropped(logging.Filter):
    """Drops a logger's own records below ``level``."""

    def __init__(self, level: int) -> None:
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= self.level


def quiet_ray_train_loggers() -> None:
    """Quiet :data:`QUIETED_RAY_TRAIN_LOGGERS`, and every report's ``Reporting training result N:
    TrainingReport(...)``: it comes from a logger named after its file, outside ``ray.train`` (whose level
    ``RunConfig.logging_config`` sets).

    Ray Train's loggers get a filter, not a level: Ray Train configures ``ray.train`` with ``logging.config`` in its
    controller and workers after this setup, and that resets the levels of every existing logger below
    ``ray.train`` (but keeps their filters)."""
    for name, level in QUIETED_RAY_TRAIN_LOGGERS.items():
        logger = logging.getLogger(name)
        if not any(isinstance(kept, BelowLevelDropped) for kept in logger.filters):
            logger.addFilter(BelowLevelDropped(level))
    logging.getLogger(ray_train_context_logger_name()).setLevel(logging.WARNING)


def ray_train_context_logger_name() -> str:
    """The name of the logger of ``ray.train.v2._internal.execution.context``: that module's ``__file__``."""
    import ray

    return os.path.join(os.path.dirname(ray.__file__), "train", "v2", "_internal", "execution", "context.py")
