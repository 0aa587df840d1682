"""MLflow helpers: where the store is, one run per training, one writer.

By default the store is embedded in the project: ``sqlite:///<project>/mlflow.db`` with artifacts in
``<project>/mlartifacts`` (both outside DVC outputs, so reruns never delete the history). ``tracking.uri`` in
params points at a remote server instead. Experiments are created once, by the driver, with an explicit
artifact location, because otherwise the first creator's working directory (perhaps a Ray session folder)
would become the artifact root. Only one process writes to a run at a time (the driver, or rank 0 of the
Ray workers while training), which SQLite needs. A run is a :class:`RunHandle` naming its id explicitly (no
global "active run"): :func:`run` opens and ends one, and Ray workers attach to the driver's
(:meth:`RunHandle.attach`).

What MLflow's UI shows comes from here too: experiments as model-training experiments with a description,
runs named after their DVC experiment or what distinguishes them (:func:`run_name_for`), the source and
commit tags of its "Source" column, and our own tags linking a training run to its DVC experiment, its inputs'
fingerprint and the pretraining run of its latent bank.

A lost store never stops training: a write to a tracking server that cannot be reached fails after a few
seconds (:data:`QUICK_HTTP_SETTINGS`, MLflow's own retries take about 4 minutes per call), warns once, and every
later write of this process to that store is skipped at once; the metrics and the run's end go to
``<project>/mlflow-unlogged/<run id>.jsonl`` instead (:func:`keep_unlogged`), which :func:`replay_unlogged` sends
once the server is back.

Browse with ``mlflow ui --backend-store-uri sqlite:///$PWD/mlflow.db`` from the project root.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Optional, Sequence

import requests
from mlflow import MlflowClient
from mlflow.entities import Dataset, DatasetInput, InputTag, Metric, Param, RunStatus
from mlflow.exceptions import MlflowException
from mlflow.protos.databricks_pb2 import RESOURCE_DOES_NOT_EXIST, ErrorCode

from endoflow.config import Params, flatten_params
from endoflow.io import ended_here, file_sha256, process_mark
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
# an experiment's kind, which MLflow's UI read before 3.17 (and Databricks' still reads)
MODEL_TRAINING_KIND = "custom_model_development"
# MLflow 3.17's UI ignores the kind: it opens every experiment in the view of its GenAI/model-training switch,
# GenAI until the browser has chosen otherwise, unless the link says which (workflowType). Its runs table shows
# the columns of a view that a link names (viewStateShareKey), kept in an experiment tag: endoflow keeps one per
# experiment, with the headline metrics as columns, and links there (runs_table_link).
MODEL_TRAINING_WORKFLOW = "machine_learning"
SHARED_VIEW_TAG_PREFIX = "mlflow.sharedViewState."
RUNS_VIEW_KEY = "endoflow-runs"
RUNS_VIEW_TAG = SHARED_VIEW_TAG_PREFIX + RUNS_VIEW_KEY
SOURCE_COLUMN = "attributes.`Source`"
# the runs table's first columns, as MLflow 3.17's UI names them: a view that orders columns lists them first
LEADING_COLUMNS = ("attributes.`Run Name`", "runDateAndNestInfo", "duration", SOURCE_COLUMN)
COLUMN_PX_PER_CHARACTER, COLUMN_PADDING_PX = 6.5, 28  # a metric column as wide as its name
# MLflow refuses a longer experiment tag value: the view keeps the newest metric columns that fit
MAX_EXPERIMENT_TAG_CHARACTERS = 20_000
# a sqlite store is browsed through `mlflow ui`, which serves here by default
MLFLOW_UI_ADDRESS = "http://127.0.0.1:5000"
# DVC sets this in the environment of every stage that `dvc exp run` (or `dvc queue start`) runs
DVC_EXPERIMENT_ENV = "DVC_EXP_NAME"
# a latent-bank run carries its bank file's digest; a training run, the run of the bank it used
LATENT_BANK_DIGEST_TAG = "endoflow.latent_bank_sha256"
LATENT_BANK_RUN_TAG = "endoflow.latent_bank_run_id"
# on a run opened for a model whose own training run is not in this store (a model file copied between machines)
MODEL_RUN_TAG = "endoflow.model_run_id"
# on an adaptation run (`endoflow adapt`): the run of the model it adapted (MLflow's parent run tag, so its UI nests it)
PARENT_RUN_TAG = "mlflow.parentRunId"
# the process that opened (or reopened) a run, as io.process_mark writes it: <process id>@<machine>
PROCESS_TAG = "endoflow.process"
# what MLflow's UI shows beside a dataset input: what the run used it for
DATASET_CONTEXT_TAG = "mlflow.data.context"
MLFLOW_DIGEST_CHARS = 32  # the store's digest column holds 36 characters
# MLflow retries a request for about 4 minutes by default (7 retries, backoff factor 2, a 120 s timeout), so a
# lost tracking server stalled training that long per call; these apply where the environment sets none
QUICK_HTTP_SETTINGS = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
                       "MLFLOW_HTTP_REQUEST_TIMEOUT": "15"}
# in the project: what a lost store did not take, one JSON object a line, per run
UNLOGGED_FOLDER = "mlflow-unlogged"

_lost_stores: dict[str, str] = {}  # tracking URI -> why this process stopped writing to it
_unlogged_files: dict[str, Path] = {}  # run id -> where its metrics go while its store is lost

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
    """A client bound to ``uri`` for runs and for registered models (no process-wide URI is set or read), its
    HTTP requests given up after a few seconds unless the environment says otherwise (:data:`QUICK_HTTP_SETTINGS`,
    read by MLflow at every request)."""
    for name, value in QUICK_HTTP_SETTINGS.items():
        os.environ.setdefault(name, value)
    return MlflowClient(tracking_uri=uri, registry_uri=uri)


# ------------------------------------------------------------------------------------ a lost store
def best_effort(uri: str, what: str, write: Callable[[], Any], run_id: Optional[str] = None) -> bool:
    """Run ``write``, which sends ``what`` to the store at ``uri``, unless this process has lost that store;
    returns whether it was written.

    The first failure loses the store: one warning on stderr (naming where the metrics of ``run_id`` are kept),
    and every later write to it is skipped at once, so a lost tracking server neither stops nor stalls training.
    """
    if uri in _lost_stores:
        return False
    try:
        write()
    except (MlflowException, requests.RequestException) as exc:  # the store's errors; not those of local files
        _lost_stores[uri] = str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__
        kept = f"; metrics are kept in {unlogged_file(run_id)}" if run_id else ""
        print(f"warning: MLflow at {uri} did not take {what} ({_lost_stores[uri]}); this process logs nothing "
              f"more to it{kept}", file=sys.stderr)
        return False
    return True


def keep_unlogged_in(run_id: str, file: str | Path) -> None:
    """Where this process keeps what the store of run ``run_id`` does not take (a Ray worker is told the driver's
    :func:`unlogged_file`)."""
    _unlogged_files[run_id] = Path(file)


def unlogged_file(run_id: str) -> Path:
    """The file that keeps what the store of ``run_id`` did not take: the one set by :func:`start_run`,
    :func:`run_for_model` or :func:`keep_unlogged_in`, else ``mlflow-unlogged/<run id>.jsonl`` here."""
    return _unlogged_files.get(run_id, Path.cwd() / UNLOGGED_FOLDER / f"{run_id}.jsonl")


def keep_unlogged(run_id: str, entry: Mapping[str, Any]) -> None:
    """Append ``entry`` (metrics at a step, or the run's end) to the run's :func:`unlogged_file`.

    Appended, not written atomically: a line cut by a crash is the only possible damage, and replaying skips it.
    """
    file = unlogged_file(run_id)
    file.parent.mkdir(parents=True, exist_ok=True)
    with open(file, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(dict(entry)) + "\n")


def replay_unlogged(uri: str, file: str | Path) -> int:
    """Send what a lost store did not take (a :func:`unlogged_file`) to the store at ``uri``: the metrics at
    their steps and times, then the run's end; the file is removed once all is sent. Returns the entries sent."""
    file = Path(file)
    run_id = file.stem
    entries = []
    for line in file.read_text(encoding="utf-8").splitlines():
        try:
            entries.append(json.loads(line))
        except ValueError:  # a line cut by a crash
            continue
    mlflow_client = client(uri)
    for entry in entries:
        if "metrics" in entry:
            metrics = [Metric(k, float(v), entry["timestamp"], entry["step"]) for k, v in entry["metrics"].items()]
            mlflow_client.log_batch(run_id, metrics=metrics)
        else:
            mlflow_client.set_terminated(run_id, status=entry["status"], end_time=entry["end_time"])
    file.unlink()
    return len(entries)


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
    """The kind (model training), the description and the runs table's view (:func:`runs_view`, no metric
    columns yet) of one of endoflow's experiments."""
    if name == params.tracking.latent_bank_experiment:
        description = ("Pretraining of endoflow's generative latent bank (StyleGAN-like, WGAN-GP) on depth maps: "
                       "one run per `pretrain_latent_bank` stage run, with its losses, sliced Wasserstein "
                       "distance and samples. Training runs name the run of the bank they used "
                       "(tag endoflow.latent_bank_run_id).")
    else:
        description = ("endoflow's joint depth and pose training: one run per `train` stage run, named after its "
                       "DVC experiment (or its ablation switches and seed), with the evaluation (abs_rel, rte_cm, "
                       "rot_deg per test set) and reconstruction results of its model (ate_cm, accuracy_cm, "
                       "completeness_2vox_pct per sequence); every figure is in each one's figures.csv.")
    return {EXPERIMENT_KIND_TAG: MODEL_TRAINING_KIND, DESCRIPTION_TAG: description,
            RUNS_VIEW_TAG: runs_view([])}


def runs_view(metric_keys: Iterable[str]) -> str:
    """The runs table's view (MLflow's UI state, JSON): the Source column and ``metric_keys`` as columns, in
    that order, each as wide as its name (the UI would cut ``eval/endoslam_colon/abs_rel`` to ``eval/endoslam_``)."""
    keys = list(metric_keys)
    columns = [f"metrics.`{key}`" for key in keys]
    return json.dumps({"selectedColumns": [SOURCE_COLUMN, *columns], "columnOrder": [*LEADING_COLUMNS, *columns],
                       "columnWidths": {column: round(COLUMN_PX_PER_CHARACTER * len(key)) + COLUMN_PADDING_PX
                                        for column, key in zip(columns, keys)}})


def runs_table_link(uri: str, experiment_id: str) -> str:
    """The address of the experiment's runs table in MLflow's UI (the store's server, else ``mlflow ui``'s
    :data:`MLFLOW_UI_ADDRESS`): :func:`runs_table_path`."""
    base = uri.rstrip("/") if uri.startswith(("http://", "https://")) else MLFLOW_UI_ADDRESS
    return f"{base}/{runs_table_path(experiment_id)}"


def runs_table_path(experiment_id: str) -> str:
    """The experiment's runs table after the UI's address, in the model-training view with endoflow's columns: a
    first visit lands there (a plain link to the experiment opens MLflow 3.17's GenAI overview)."""
    return (f"#/experiments/{experiment_id}/runs?workflowType={MODEL_TRAINING_WORKFLOW}"
            f"&viewStateShareKey={RUNS_VIEW_KEY}")


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
              fingerprint: Optional[str] = None) -> RunHandle:
    """Open a run with flat params and the git commit, left open (:func:`run` also ends it).

    With ``fingerprint``, an unfinished run of the same experiment carrying the same fingerprint (an
    interrupted training being resumed) is reopened instead, so one training stays one run. What the store
    does not take of the run is kept in the project (:func:`project_unlogged_file`). Runs of the experiment
    left RUNNING by a process of this machine that was killed are marked KILLED first
    (:func:`end_abandoned_runs`).
    """
    run_id = _open_run(params, project_root, experiment, run_name, fingerprint)
    handle = RunHandle.attach(tracking_uri(params, project_root), run_id,
                              project_unlogged_file(project_root, run_id))
    handle.log_params(flat_params(params))
    print(f"[mlflow] run {run_name!r}: {browse_hint(handle.uri, ensure_experiment(params, project_root, experiment))}",
          file=sys.stderr)
    return handle


@contextlib.contextmanager
def run(params: Params, project_root: str | Path, experiment: str, run_name: str,
        fingerprint: Optional[str] = None) -> Iterator[RunHandle]:
    """Within: the run :func:`start_run` opens (or reopens). It ends FINISHED, FAILED on an error (a rerun with
    the same fingerprint reopens it) or KILLED on an interrupt; the error is re-raised, never hidden by the end
    (:meth:`RunHandle.end`)."""
    handle = start_run(params, project_root, experiment, run_name, fingerprint)
    try:
        yield handle
    except KeyboardInterrupt:
        handle.end(RunStatus.KILLED)
        raise
    except BaseException:
        handle.end(RunStatus.FAILED)
        raise
    handle.end(RunStatus.FINISHED)


def browse_hint(uri: str, experiment_id: str) -> str:
    """Where a person sees the experiment's runs: its runs table's link, after ``mlflow ui`` for a local store."""
    link = runs_table_link(uri, experiment_id)
    return link if uri.startswith(("http://", "https://")) else f"`mlflow ui --backend-store-uri {uri}`, then {link}"


def _open_run(params: Params, project_root: str | Path, experiment: str, run_name: str,
              fingerprint: Optional[str]) -> str:
    uri = tracking_uri(params, project_root)
    mlflow_client = client(uri)
    experiment_id = ensure_experiment(params, project_root, experiment)
    end_abandoned_runs(uri, experiment_id)
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
            mlflow_client.set_tag(run_id, PROCESS_TAG, process_mark())
            return run_id
    tags = {"mlflow.runName": run_name, PROCESS_TAG: process_mark(), **source_tags(project_root)}
    if fingerprint is not None:
        tags[FINGERPRINT_TAG] = fingerprint
    if dvc_experiment_name():
        tags[DVC_EXPERIMENT_TAG] = dvc_experiment_name()
    return mlflow_client.create_run(experiment_id, tags=tags, run_name=run_name).info.run_id


def end_abandoned_runs(uri: str, experiment_id: str) -> list[str]:
    """Mark KILLED the runs of the experiment still RUNNING whose process (:data:`PROCESS_TAG`) has ended on this
    machine: it was killed before it could end its run (a killed run cannot end it itself). Returns their ids."""
    mlflow_client = client(uri)
    running = mlflow_client.search_runs([experiment_id], filter_string="attributes.status = 'RUNNING'",
                                        max_results=1000)
    abandoned = [run.info.run_id for run in running if ended_here(run.data.tags.get(PROCESS_TAG, ""))]
    for run_id in abandoned:
        mlflow_client.set_terminated(run_id, status=RunStatus.to_string(RunStatus.KILLED))
    return abandoned


def project_unlogged_file(project_root: str | Path, run_id: str) -> Path:
    """``<project>/mlflow-unlogged/<run id>.jsonl`` (the project whose MLflow store the run uses)."""
    return home_project(project_root) / UNLOGGED_FOLDER / f"{run_id}.jsonl"


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


def run_for_model(params: Params, project_root: str | Path, model_run_id: Optional[str],
                  run_name: str) -> RunHandle:
    """The run to log a model's results into: its training run ``model_run_id`` when this store holds it.

    Otherwise (a model trained elsewhere, or a fresh store) a run of ``tracking.experiment`` tagged with the
    missing id (:data:`MODEL_RUN_TAG`), opened once and found again by every later caller for the same model,
    with a warning on stderr naming the missing run and the store. What the store does not take of the run is
    kept in the project (:func:`project_unlogged_file`).
    """
    run_id = _model_run(params, project_root, model_run_id, run_name)
    return RunHandle.attach(tracking_uri(params, project_root), run_id, project_unlogged_file(project_root, run_id))


def _model_run(params: Params, project_root: str | Path, model_run_id: Optional[str], run_name: str) -> str:
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


def link_latent_bank(params: Params, run: RunHandle, bank_digest: str) -> Optional[str]:
    """Tag training run ``run`` with the digest of the latent bank file it uses and, when its store holds the
    pretraining run that wrote that file, with that run's id; returns the id (``None`` if not found)."""
    tags = {LATENT_BANK_DIGEST_TAG: bank_digest}
    mlflow_client = client(run.uri)
    experiment = mlflow_client.get_experiment_by_name(params.tracking.latent_bank_experiment)
    found = mlflow_client.search_runs([experiment.experiment_id],
                                      filter_string=f"tags.`{LATENT_BANK_DIGEST_TAG}` = '{bank_digest}'",
                                      order_by=["attributes.start_time DESC"], max_results=1) if experiment else []
    if found:
        tags[LATENT_BANK_RUN_TAG] = found[0].info.run_id
    run.set_tags(tags)
    return found[0].info.run_id if found else None


def metric_key(key: str) -> str:
    """MLflow keys allow letters, digits, ``_ - . / space``; anything else becomes ``_``."""
    return "".join(c if c.isalnum() or c in "_-./ " else "_" for c in key)


# ------------------------------------------------------------------------------------------- a run
@dataclass(frozen=True)
class RunHandle:
    """One MLflow run of the store at ``uri``, named by its explicit id (no process-wide active run, so a Ray
    worker logs into the run its driver opened). Every write is :func:`best_effort`: a lost store warns once and
    what it did not take of the metrics and the end is kept in :meth:`unlogged_file`."""

    uri: str
    run_id: str

    @classmethod
    def attach(cls, uri: str, run_id: str, unlogged: Optional[str | Path] = None) -> RunHandle:
        """The run ``run_id`` opened elsewhere (by the driver of a Ray training; the training run a model file
        names); ``unlogged``: where this process keeps what the store does not take (the opener's
        :meth:`unlogged_file`), else :func:`unlogged_file`'s default."""
        if unlogged:
            keep_unlogged_in(run_id, unlogged)
        return cls(uri, run_id)

    def unlogged_file(self) -> Path:
        return unlogged_file(self.run_id)

    def best_effort(self, what: str, write: Callable[[], Any]) -> bool:
        """:func:`best_effort` for ``what`` of this run."""
        return best_effort(self.uri, what, write, self.run_id)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        """Set (or overwrite) ``tags`` on the run."""
        def write() -> None:
            mlflow_client = client(self.uri)
            for key, value in tags.items():
                mlflow_client.set_tag(self.run_id, key, value)

        self.best_effort(f"tags of run {self.run_id}", write)

    def log_params(self, values: Mapping[str, str]) -> None:
        """Log params in batches (MLflow caps a batch at 100 params)."""
        items = [Param(k, v) for k, v in values.items()]

        def write() -> None:
            mlflow_client = client(self.uri)
            for start in range(0, len(items), 100):
                mlflow_client.log_batch(self.run_id, params=items[start:start + 100])

        self.best_effort(f"the params of run {self.run_id}", write)

    def log_metrics(self, values: Mapping[str, float], step: int = 0) -> None:
        """Log ``values`` at ``step`` in one request (keys are sanitised to MLflow's allowed characters); what the
        store does not take is kept in the run's :meth:`unlogged_file`."""
        now = int(time.time() * 1000)
        metrics = [Metric(metric_key(k), float(v), now, step) for k, v in values.items()]

        def write() -> None:
            mlflow_client = client(self.uri)
            for start in range(0, len(metrics), 1000):
                mlflow_client.log_batch(self.run_id, metrics=metrics[start:start + 1000])

        if not self.best_effort(f"metrics of run {self.run_id}", write):
            keep_unlogged(self.run_id, {"step": step, "timestamp": now,
                                        "metrics": {m.key: m.value for m in metrics}})

    def show_in_runs_table(self, metric_keys: Iterable[str]) -> None:
        """Add ``metric_keys`` (after those it has) to the columns of the runs table's view of the run's
        experiment."""
        def write() -> None:
            mlflow_client = client(self.uri)
            experiment = mlflow_client.get_experiment(mlflow_client.get_run(self.run_id).info.experiment_id)
            view = json.loads(experiment.tags.get(RUNS_VIEW_TAG, runs_view([])))
            shown = [column for column in view.get("selectedColumns", []) if column.startswith("metrics.")]
            wanted = list(dict.fromkeys([*(column[len("metrics.`"):-1] for column in shown), *metric_keys]))
            updated = runs_view(wanted)
            while len(updated) > MAX_EXPERIMENT_TAG_CHARACTERS:
                wanted = wanted[1:]
                updated = runs_view(wanted)
            if updated != experiment.tags.get(RUNS_VIEW_TAG):
                mlflow_client.set_experiment_tag(experiment.experiment_id, RUNS_VIEW_TAG, updated)

        self.best_effort(f"the runs table's columns of run {self.run_id}'s experiment", write)

    def log_shards_input(self, manifest: str, name: str, context: str) -> str:
        """Log a shard folder as a dataset input of the run (the "Datasets used" of MLflow's UI): named ``name``,
        its source the manifest at ``manifest`` (a path or an fsspec URL), its digest the manifest's SHA-256
        (which covers every shard's SHA-256 and sample count), ``context`` what the run used it for
        (``training``, ``evaluation``). Logging the same input again (a resumed run) adds nothing. Returns the
        digest."""
        hexdigest = file_sha256(manifest)[:MLFLOW_DIGEST_CHARS]
        # the source types of MLflow's own artifact sources: "local" for a path, the URL's scheme otherwise
        source_type, location = ((manifest.split("://", 1)[0], manifest) if "://" in manifest
                                 else ("local", str(Path(manifest).resolve())))
        dataset = Dataset(name=name, digest=hexdigest, source_type=source_type,
                          source=json.dumps({"uri": location}))
        dataset_input = DatasetInput(dataset, tags=[InputTag(DATASET_CONTEXT_TAG, context)])
        self.best_effort(f"the dataset input of run {self.run_id}",
                         lambda: client(self.uri).log_inputs(self.run_id, datasets=[dataset_input]))
        return hexdigest

    def log_dict(self, values: Mapping[str, Any], artifact_file: str) -> None:
        """Save ``values`` as a JSON artifact."""
        self.best_effort(f"{artifact_file} of run {self.run_id}",
                         lambda: client(self.uri).log_dict(self.run_id, dict(values), artifact_file))

    def log_table(self, rows: Sequence[Mapping[str, Any]], artifact_file: str) -> None:
        """Save ``rows`` (one dict per row, the first one's keys as columns) as a CSV artifact, which MLflow's UI
        shows as a table: where one-off figures go, so that the run's charts are its curves."""
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]) if rows else [], lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        self.best_effort(f"{artifact_file} of run {self.run_id}",
                         lambda: client(self.uri).log_text(self.run_id, buffer.getvalue(), artifact_file))

    def log_figure(self, figure: Any, artifact_file: str) -> None:
        """Save a matplotlib figure as a PNG artifact."""
        self.best_effort(f"{artifact_file} of run {self.run_id}",
                         lambda: client(self.uri).log_figure(self.run_id, figure, artifact_file))

    def log_artifact(self, path: str | Path, artifact_path: Optional[str] = None) -> None:
        """Upload a file or a folder into the run's artifacts (a lost store leaves them where they are)."""
        def write() -> None:
            mlflow_client = client(self.uri)
            if Path(path).is_dir():
                mlflow_client.log_artifacts(self.run_id, str(path), artifact_path)
            else:
                mlflow_client.log_artifact(self.run_id, str(path), artifact_path)

        self.best_effort(f"{path} for run {self.run_id}", write)

    def end(self, status: int = RunStatus.FINISHED) -> None:
        """Mark the run ``status`` (a :class:`RunStatus`: FAILED and KILLED runs are reopened by a rerun with the
        same fingerprint); with its store lost, the end is kept in the run's :meth:`unlogged_file`, and an error
        of the run stays the one raised."""
        name = RunStatus.to_string(status)
        now = int(time.time() * 1000)
        if not self.best_effort(f"the end of run {self.run_id}",
                                lambda: client(self.uri).set_terminated(self.run_id, status=name, end_time=now)):
            keep_unlogged(self.run_id, {"status": name, "end_time": now})
