"""A cluster's runs log through an MLflow tracking server (`tracking.uri`), since rank 0 may run on a node that
cannot reach a SQLite file on the head: here a real `mlflow server` on localhost, with its own store and
artifact folder, and nothing written into the project."""

from __future__ import annotations

import socket
import subprocess
import time
import urllib.request
from pathlib import Path
from typing import Iterator

import pytest

from endoflow import tracking
from endoflow.config import Params
from tests.module_temp import ModuleTemp
from tests.project_clone import VENV_BIN

SERVER_START_TIMEOUT_S = 120


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="module")
def server(module_tmp: ModuleTemp) -> Iterator[tuple[str, Path]]:
    """``(uri, folder)`` of an `mlflow server` listening on 127.0.0.1, storing into ``folder``."""
    folder = module_tmp("mlflow_server")
    port = free_port()
    log = open(folder / "server.log", "w")
    process = subprocess.Popen(
        [str(VENV_BIN / "mlflow"), "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
         "--backend-store-uri", f"sqlite:///{folder / 'server.db'}",
         "--artifacts-destination", str(folder / "artifacts")],
        stdout=log, stderr=subprocess.STDOUT)
    uri = f"http://127.0.0.1:{port}"
    try:
        wait_until_healthy(uri, process, folder / "server.log")
        yield uri, folder
    finally:
        process.terminate()
        process.wait(timeout=30)
        log.close()


def wait_until_healthy(uri: str, process: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + SERVER_START_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"mlflow server exited ({process.returncode}):\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"{uri}/health", timeout=2) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.5)
    raise TimeoutError(f"mlflow server at {uri} not healthy after {SERVER_START_TIMEOUT_S} s:\n"
                       f"{log.read_text()[-3000:]}")


def test_a_run_logs_params_metrics_and_artifacts_through_the_server(server, tmp_path: Path):
    uri, folder = server
    params = Params()
    params.tracking.uri = uri
    project = tmp_path / "project"
    project.mkdir()
    assert tracking.tracking_uri(params, project) == uri
    picture = tmp_path / "curves.png"
    picture.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with tracking.run(params, project, params.tracking.experiment, "train bank vae seed0", "f1") as opened:
        opened.log_metrics({"loss/total": 0.5}, step=7)
        opened.log_artifact(picture, "plots/train")
    run_id = opened.run_id

    # read back through another client, as the MLflow UI of the server would show it
    run = tracking.client(uri).get_run(run_id)
    assert run.info.status == "FINISHED" and run.info.run_name == "train bank vae seed0"
    assert run.data.metrics["loss/total"] == 0.5 and run.data.params["model.latent_bank"] == "True"
    experiment = tracking.client(uri).get_experiment(run.info.experiment_id)
    assert experiment.tags[tracking.EXPERIMENT_KIND_TAG] == tracking.MODEL_TRAINING_KIND
    downloaded = tracking.client(uri).download_artifacts(run_id, "plots/train/curves.png", str(tmp_path))
    assert Path(downloaded).read_bytes() == picture.read_bytes()
    # the server stored it (its artifacts proxied through HTTP); the project holds no store of its own
    assert list((folder / "artifacts").rglob("curves.png"))
    assert not (project / "mlflow.db").exists() and not (project / "mlartifacts").exists()


def test_results_of_a_model_trained_elsewhere_find_one_run_on_the_server(server, tmp_path: Path, capsys):
    uri, _ = server
    params = Params()
    params.tracking.uri = uri
    first = tracking.run_for_model(params, tmp_path, "0123456789abcdef0123456789abcdef", "evaluate")
    assert "is not in http://127.0.0.1" in capsys.readouterr().err
    assert tracking.run_for_model(params, tmp_path, "0123456789abcdef0123456789abcdef", "evaluate") == first
