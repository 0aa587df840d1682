"""MLflow helpers: where the store is, one run per training, one writer.

By default the store is embedded in the project: ``sqlite:///<project>/mlflow.db`` with artifacts in
``<project>/mlartifacts`` (both outside DVC outputs, so reruns never delete the history). ``tracking.uri`` in
params points at a remote server instead. Experiments are created once, by the driver, with an explicit
artifact location, because otherwise the first creator's working directory (perhaps a Ray session folder)
would become the artifact root. Only one process writes to a run at a time (the driver, or rank 0 of the
Ray workers while training), which SQLite needs. Every call names its run id explicitly (no global
"active run"), so Ray workers can log into the driver's run.

What MLflow's UI shows comes from here too: experiments as model-training experiments with a description,
runs named after their DVC experiment or what distinguishes them (:func:`run_name_for`), the source and
commit tags of its "Source" column, and our own tags linking a training run to its DVC experiment, its inputs'
fingerprint and the pretraining run of its latent bank.

Browse with ``mlflow ui --backend-store-uri sqlite:///$PWD/mlflow.db`` from the project root.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional

from mlflow import MlflowClient
from mlflow.entities import Dataset, DatasetInput, InputTag, Metric, Param, RunStatus
from mlflow.exceptions import MlflowException
from mlflow.protos.databricks_pb2 import RESOURCE_DOES_NOT_EXIST, ErrorCode

from endoflow.config import Params, flatten_params
from endoflow.io import file_sha256
from endoflow.locations import home_project

MLFLOW_PARAM_LIMIT = 6000  # characters MLflow accepts in one param value
FINGERPRINT_TAG = "endoflow.fingerprint"
DVC_EXPERIMENT_TAG = "endoflow.dvc_experiment"
# the tags MLflow's UI reads for a run's "Source" column and an experiment's kind and description
GIT_COMMIT_TAG = "mlflow.source.git.commit"
SOURCE_NAME_TAG = "mlflow.source.name"
SOURCE_TYPE_TAG = "mlflow.source.type"
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
DESCRIPTION_TAG = "mlflow.note.content"
# without a kind, MLflow 3's UI opens an experiment in its GenAI view (traces, prompts)
MODEL_TRAINING_KIND = "custom_model_development"
# DVC sets this in the environment of every stage that `dvc exp run` (or `dvc queue start`) runs
DVC_EXPERIMENT_ENV = "DVC_EXP_NAME"
# a latent-bank run carries its bank file's digest; a training run, the run of the bank it used
LATENT_BANK_DIGEST_TAG = "endoflow.latent_bank_sha256"
LATENT_BANK_RUN_TAG = "endoflow.latent_bank_run_id"
# on a run opened for a model whose own training run is not in this store (a model file copied between machines)
MODEL_RUN_TAG = "endoflow.model_run_id"
# what MLflow's UI shows beside a dataset input: what the run used it for
DATASET_CONTEXT_TAG = "mlflow.data.context"
MLFLOW_DIGEST_CHARS = 32  # the store's digest column holds 36 characters

# MLflow announces at INFO, on the terminal, each table it creates in a new store: library noise
logging.getLogger("mlflow.store.db.utils").setLevel(logging.WARNING)


def tracking_uri(params: Params, project_root: str | Path) -> str:
    """``params.tracking.uri``, or the embedded SQLite store at the root of the project (absolute; for a queued
    DVC experiment, the project it was queued in: :func:`endoflow.locations.home_project`)."""
    if params.tracking.uri:
        return params.tracking.uri
    return f"sqlite:///{home_project(project_root) / 'mlflow.db'}"


def artifact_location(params: Params, project_root: str | Path) -> Optional[str]:
    """Artifact root for new experiments: ``<project>/mlartifacts`` locally, the server's default remotely."""
    if params.tracking.uri:
        return None
    return (home_project(project_root) / "mlartifacts").as_uri()


def client(uri: str) -> MlflowClient:
    """A client bound to ``uri`` for runs and for registered models (no process-wide URI is set or read)."""
    return MlflowClient(tracking_uri=uri, registry_uri=uri)


def ensure_experiment(params: Params, project_root: str | Path, name: str) -> str:
    """Id of experiment ``name``, created the first time with the project's artifact location, as a
    model-training experiment with a description (:func:`experiment_tags`); an older experiment without them
    gets them."""
    mlflow_client = client(tracking_uri(params, project_root))
    tags = experiment_tags(params, name)
    experiment = mlflow_client.get_experiment_by_name(name)
    if experiment is None:
        return mlflow_client.create_experiment(name, artifact_location=artifact_location(params, project_root),
                                               tags=tags)
    for key, value in tags.items():
        if key not in experiment.tags:
            mlflow_client.set_experiment_tag(experiment.experiment_id, key, value)
    return experiment.experiment_id


def experiment_tags(params: Params, name: str) -> dict[str, str]:
    """The kind (model training) and the description MLflow shows for one of endoflow's experiments."""
    if name == params.tracking.latent_bank_experiment:
        description = ("Pretraining of endoflow's generative latent bank (StyleGAN-like, WGAN-GP) on depth maps: "
                       "one run per `pretrain_latent_bank` stage run, with its losses, sliced Wasserstein "
                       "distance and samples. Training runs name the run of the bank they used "
                       "(tag endoflow.latent_bank_run_id).")
    else:
        description = ("endoflow's joint depth and pose training: one run per `train` stage run, named after its "
                       "DVC experiment (or its ablation switches and seed), with the evaluation (abs_rel, rte, "
                       "rot per test set) and reconstruction results of its model.")
    return {EXPERIMENT_KIND_TAG: MODEL_TRAINING_KIND, DESCRIPTION_TAG: description}


def dvc_experiment_name() -> Optional[str]:
    """The DVC experiment this process runs in, if any."""
    return os.environ.get(DVC_EXPERIMENT_ENV) or None


def run_name_for(stage: str, distinguishing: Iterable[str]) -> str:
    """A run's name: its DVC experiment's where there is one, else the stage and what distinguishes the run
    (``train bank no-vae seed1``), so that the runs of an ablation differ in MLflow's table."""
    return dvc_experiment_name() or " ".join([stage, *distinguishing])


def ablation_switches(params: Params) -> list[str]:
    """``bank``/``no-bank`` and ``vae``/``no-vae``: the model's ablation switches, as run names show them."""
    return [word if on else f"no-{word}" for word, on in (("bank", params.model.latent_bank),
                                                           ("vae", params.model.pose_vae))]


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
    tags = {"mlflow.runName": run_name, **source_tags(project_root)}
    if fingerprint is not None:
        tags[FINGERPRINT_TAG] = fingerprint
    if dvc_experiment_name():
        tags[DVC_EXPERIMENT_TAG] = dvc_experiment_name()
    run = mlflow_client.create_run(experiment_id, tags=tags, run_name=run_name)
    log_params(uri, run.info.run_id, flat_params(params))
    return run.info.run_id


def source_tags(project_root: str | Path) -> dict[str, str]:
    """The tags of MLflow's "Source" column: the script that runs (relative to the project) and the commit."""
    script = Path(sys.argv[0]).resolve()
    root = Path(project_root).resolve()
    tags = {SOURCE_NAME_TAG: str(script.relative_to(root)) if script.is_relative_to(root) else script.name,
            SOURCE_TYPE_TAG: "LOCAL"}
    commit = git_commit(project_root)
    if commit:
        tags[GIT_COMMIT_TAG] = commit
    return tags


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


def set_tags(uri: str, run_id: str, tags: Mapping[str, str]) -> None:
    """Set (or overwrite) ``tags`` on the run."""
    mlflow_client = client(uri)
    for key, value in tags.items():
        mlflow_client.set_tag(run_id, key, value)


def link_latent_bank(params: Params, project_root: str | Path, run_id: str, bank_digest: str) -> Optional[str]:
    """Tag training run ``run_id`` with the digest of the latent bank file it uses and, when this store holds
    the pretraining run that wrote that file, with that run's id; returns the id (``None`` if not found)."""
    uri = tracking_uri(params, project_root)
    tags = {LATENT_BANK_DIGEST_TAG: bank_digest}
    experiment = client(uri).get_experiment_by_name(params.tracking.latent_bank_experiment)
    found = client(uri).search_runs([experiment.experiment_id],
                                    filter_string=f"tags.`{LATENT_BANK_DIGEST_TAG}` = '{bank_digest}'",
                                    order_by=["attributes.start_time DESC"], max_results=1) if experiment else []
    if found:
        tags[LATENT_BANK_RUN_TAG] = found[0].info.run_id
    set_tags(uri, run_id, tags)
    return found[0].info.run_id if found else None


def log_shards_input(uri: str, run_id: str, manifest: str, name: str, context: str) -> str:
    """Log a shard folder as a dataset input of the run (the "Datasets used" of MLflow's UI): named ``name``,
    its source the manifest at ``manifest`` (a path or an fsspec URL), its digest the manifest's SHA-256 (which
    covers every shard's SHA-256 and sample count), ``context`` what the run used it for (``training``,
    ``evaluation``). Logging the same input again (a resumed run) adds nothing. Returns the digest."""
    hexdigest = file_sha256(manifest)[:MLFLOW_DIGEST_CHARS]
    # the source types of MLflow's own artifact sources: "local" for a path, the URL's scheme otherwise
    source_type, location = ((manifest.split("://", 1)[0], manifest) if "://" in manifest
                             else ("local", str(Path(manifest).resolve())))
    dataset = Dataset(name=name, digest=hexdigest, source_type=source_type, source=json.dumps({"uri": location}))
    dataset_input = DatasetInput(dataset, tags=[InputTag(DATASET_CONTEXT_TAG, context)])
    client(uri).log_inputs(run_id, datasets=[dataset_input])
    return hexdigest


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


def log_dict(uri: str, run_id: str, values: Mapping[str, Any], artifact_file: str) -> None:
    """Save ``values`` as a JSON artifact."""
    client(uri).log_dict(run_id, dict(values), artifact_file)


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
