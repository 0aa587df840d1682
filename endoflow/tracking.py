"""MLflow helpers: where the store is, one run per training, one writer.

By default the store is embedded in the project: ``sqlite:///<project>/mlflow.db`` with artifacts in
``<project>/mlartifacts`` (both outside DVC outputs, so reruns never delete the history). ``tracking.uri`` in
params points at a remote server instead. Experiments are created once, by the driver, with an explicit
artifact location, because otherwise the first creator's working directory (perhaps a Ray session folder)
would become the artifact root. Only one process writes to a run at a time (the driver, or rank 0 of the
Ray workers while training), which SQLite needs. Every call names its run id explicitly (no global
"active run"), so Ray workers can log into the driver's run.

Browse with ``mlflow ui --backend-store-uri sqlite:///$PWD/mlflow.db`` from the project root.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Mapping, Optional

from mlflow import MlflowClient
from mlflow.entities import Metric, Param, RunStatus
from mlflow.exceptions import MlflowException
from mlflow.protos.databricks_pb2 import RESOURCE_DOES_NOT_EXIST, ErrorCode

from endoflow.config import Params, flatten_params

MLFLOW_PARAM_LIMIT = 6000  # characters MLflow accepts in one param value
FINGERPRINT_TAG = "endoflow.fingerprint"
GIT_COMMIT_TAG = "mlflow.source.git.commit"
# on a run opened for a model whose own training run is not in this store (a model file copied between machines)
MODEL_RUN_TAG = "endoflow.model_run_id"


def tracking_uri(params: Params, project_root: str | Path) -> str:
    """``params.tracking.uri``, or the embedded SQLite store at the project root (absolute)."""
    if params.tracking.uri:
        return params.tracking.uri
    return f"sqlite:///{Path(project_root).resolve() / 'mlflow.db'}"


def artifact_location(params: Params, project_root: str | Path) -> Optional[str]:
    """Artifact root for new experiments: ``<project>/mlartifacts`` locally, the server's default remotely."""
    if params.tracking.uri:
        return None
    return (Path(project_root).resolve() / "mlartifacts").as_uri()


def client(uri: str) -> MlflowClient:
    """A client bound to ``uri`` (no process-wide tracking URI is set)."""
    return MlflowClient(tracking_uri=uri)


def ensure_experiment(params: Params, project_root: str | Path, name: str) -> str:
    """Id of experiment ``name``, creating it with the project's artifact location the first time."""
    mlflow_client = client(tracking_uri(params, project_root))
    experiment = mlflow_client.get_experiment_by_name(name)
    if experiment is not None:
        return experiment.experiment_id
    return mlflow_client.create_experiment(name, artifact_location=artifact_location(params, project_root))


def flat_params(params: Params) -> dict[str, str]:
    """:func:`~endoflow.config.flatten_params` as MLflow param strings (cut to MLflow's length limit)."""
    return {key: str(value)[:MLFLOW_PARAM_LIMIT] for key, value in flatten_params(params).items()}


def git_commit(project_root: str | Path) -> Optional[str]:
    """HEAD's commit (with ``-dirty`` when the work tree differs), or ``None`` outside git / before a commit."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=project_root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=project_root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return f"{head}-dirty" if dirty else head


def start_run(params: Params, project_root: str | Path, experiment: str, run_name: str,
              fingerprint: Optional[str] = None) -> str:
    """Open a run with flat params and the git commit; returns its id.

    With ``fingerprint``, an unfinished run of the same experiment carrying the same fingerprint (an
    interrupted training being resumed) is reopened instead, so one training stays one run.
    """
    uri = tracking_uri(params, project_root)
    mlflow_client = client(uri)
    experiment_id = ensure_experiment(params, project_root, experiment)
    if fingerprint is not None:
        unfinished = mlflow_client.search_runs(
            [experiment_id],
            filter_string=f"tags.`{FINGERPRINT_TAG}` = '{fingerprint}' and attributes.status != 'FINISHED'",
            order_by=["attributes.start_time DESC"],
            max_results=1,
        )
        if unfinished:
            run_id = unfinished[0].info.run_id
            mlflow_client.update_run(run_id, status="RUNNING")
            return run_id
    tags = {"mlflow.runName": run_name}
    commit = git_commit(project_root)
    if commit:
        tags[GIT_COMMIT_TAG] = commit
    if fingerprint is not None:
        tags[FINGERPRINT_TAG] = fingerprint
    run = mlflow_client.create_run(experiment_id, tags=tags, run_name=run_name)
    log_params(uri, run.info.run_id, flat_params(params))
    return run.info.run_id


def run_exists(uri: str, run_id: str) -> bool:
    """Whether the store at ``uri`` holds the run ``run_id`` (other store errors propagate)."""
    try:
        client(uri).get_run(run_id)
    except MlflowException as exc:
        if exc.error_code == ErrorCode.Name(RESOURCE_DOES_NOT_EXIST):
            return False
        raise
    return True


def run_for_model(params: Params, project_root: str | Path, model_run_id: Optional[str], run_name: str) -> str:
    """The run to log a model's results into: its training run ``model_run_id`` when this store holds it.

    Otherwise (a model trained elsewhere, or a fresh store) a run of ``tracking.experiment`` tagged with the
    missing id (:data:`MODEL_RUN_TAG`), opened once and found again by every later caller for the same model,
    with a warning on stderr naming the missing run and the store.
    """
    uri = tracking_uri(params, project_root)
    if model_run_id and run_exists(uri, model_run_id):
        return model_run_id
    experiment_id = ensure_experiment(params, project_root, params.tracking.experiment)
    marker = model_run_id or "none"
    found = client(uri).search_runs([experiment_id], filter_string=f"tags.`{MODEL_RUN_TAG}` = '{marker}'",
                                    order_by=["attributes.start_time DESC"], max_results=1)
    if found:
        return found[0].info.run_id
    missing = f"its training run {model_run_id} is not in {uri}" if model_run_id else "it names no training run"
    print(f"warning: the model's results go to a new MLflow run ({run_name}): {missing} "
          f"(a model file copied from another machine?)", file=sys.stderr)
    run = client(uri).create_run(experiment_id, tags={"mlflow.runName": run_name, MODEL_RUN_TAG: marker},
                                 run_name=run_name)
    return run.info.run_id


def log_params(uri: str, run_id: str, values: Mapping[str, str]) -> None:
    """Log params in batches (MLflow caps a batch at 100 params)."""
    items = [Param(k, v) for k, v in values.items()]
    mlflow_client = client(uri)
    for start in range(0, len(items), 100):
        mlflow_client.log_batch(run_id, params=items[start:start + 100])


def log_metrics(uri: str, run_id: str, values: Mapping[str, float], step: int = 0) -> None:
    """Log ``values`` at ``step`` in one request (keys are sanitised to MLflow's allowed characters)."""
    now = int(time.time() * 1000)
    metrics = [Metric(metric_key(k), float(v), now, step) for k, v in values.items()]
    mlflow_client = client(uri)
    for start in range(0, len(metrics), 1000):
        mlflow_client.log_batch(run_id, metrics=metrics[start:start + 1000])


def metric_key(key: str) -> str:
    """MLflow keys allow letters, digits, ``_ - . / space``; anything else becomes ``_``."""
    return "".join(c if c.isalnum() or c in "_-./ " else "_" for c in key)


def log_figure(uri: str, run_id: str, figure: Any, artifact_file: str) -> None:
    """Save a matplotlib figure as a PNG artifact."""
    client(uri).log_figure(run_id, figure, artifact_file)


def log_artifact(uri: str, run_id: str, path: str | Path, artifact_path: Optional[str] = None) -> None:
    """Upload a file or a folder into the run's artifacts."""
    mlflow_client = client(uri)
    if Path(path).is_dir():
        mlflow_client.log_artifacts(run_id, str(path), artifact_path)
    else:
        mlflow_client.log_artifact(run_id, str(path), artifact_path)


def end_run(uri: str, run_id: str, failed: bool = False) -> None:
    """Mark the run FINISHED (or FAILED, so a rerun with the same inputs reopens it)."""
    status = RunStatus.to_string(RunStatus.FAILED if failed else RunStatus.FINISHED)
    client(uri).set_terminated(run_id, status=status)
