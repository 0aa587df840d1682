"""What MLflow's UI shows of endoflow's runs: a link that opens an experiment's runs table in the model-training
view (MLflow 3.17 opens every experiment in its GenAI view unless told), with the headline metrics as columns
from a view kept in an experiment tag; one-off figures as a table, not as one-point charts."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from endoflow import tracking
from endoflow.config import Params


def shown_metrics(uri: str, experiment_id: str) -> list[str]:
    """The metric columns of the experiment's runs table view, in order."""
    view = json.loads(tracking.client(uri).get_experiment(experiment_id).tags[tracking.RUNS_VIEW_TAG])
    columns = view["selectedColumns"]
    assert columns[0] == tracking.SOURCE_COLUMN
    assert view["columnOrder"] == [*tracking.LEADING_COLUMNS, *columns[1:]]
    assert set(view["columnWidths"]) == set(columns[1:])
    return [column[len("metrics.`"):-1] for column in columns[1:]]


def test_the_link_opens_the_runs_table_in_the_model_training_view_with_endoflows_columns():
    assert tracking.runs_table_link("sqlite:////project/mlflow.db", "2") == (
        "http://127.0.0.1:5000/#/experiments/2/runs?workflowType=machine_learning&viewStateShareKey=endoflow-runs")
    assert tracking.runs_table_link("http://mlflow.example:5000/", "7").startswith(
        "http://mlflow.example:5000/#/experiments/7/runs?")
    assert tracking.RUNS_VIEW_TAG == "mlflow.sharedViewState.endoflow-runs"  # where the UI looks the key up


def test_stages_add_their_headline_to_the_runs_tables_columns_once_each_in_order(tmp_path: Path, capsys):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    run = tracking.start_run(params, tmp_path, "exp", "train")
    experiment_id = tracking.client(uri).get_run(run.run_id).info.experiment_id
    assert tracking.runs_table_link(uri, experiment_id) in capsys.readouterr().err
    assert shown_metrics(uri, experiment_id) == []  # the view exists from the start: the link always opens
    run.show_in_runs_table(["test/simcol_3/abs_rel", "test/simcol_3/rte_cm"])
    run.show_in_runs_table(["reconstruct/simcol_S5/ate_cm", "test/simcol_3/abs_rel"])
    assert shown_metrics(uri, experiment_id) == ["test/simcol_3/abs_rel", "test/simcol_3/rte_cm",
                                                 "reconstruct/simcol_S5/ate_cm"]
    view = json.loads(tracking.client(uri).get_experiment(experiment_id).tags[tracking.RUNS_VIEW_TAG])
    assert view["columnWidths"]["metrics.`reconstruct/simcol_S5/ate_cm`"] > view["columnWidths"][
        "metrics.`test/simcol_3/abs_rel`"]  # each as wide as its name


def test_the_view_keeps_the_newest_columns_within_mlflows_tag_size(tmp_path: Path):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    run = tracking.start_run(params, tmp_path, "exp", "train")
    keys = [f"reconstruct/a_sequence_with_a_rather_long_name_{i:03d}/completeness_2vox_pct" for i in range(150)]
    run.show_in_runs_table(keys)
    experiment_id = tracking.client(uri).get_run(run.run_id).info.experiment_id
    shown = shown_metrics(uri, experiment_id)
    assert 50 < len(shown) < len(keys) and shown == keys[-len(shown):]
    run.log_metrics({"loss/total": 1.0})  # the store was not given up on
    assert tracking.client(uri).get_run(run.run_id).data.metrics == {"loss/total": 1.0}


def test_one_off_figures_are_a_csv_table_artifact(tmp_path: Path):
    params = Params()
    uri = tracking.tracking_uri(params, tmp_path)
    run = tracking.start_run(params, tmp_path, "exp", "train")
    rows = [{"protocol": "depth_paper", "method": "model", "metric": "abs_rel", "value": 0.25},
            {"protocol": "pose_simcol", "method": "model", "metric": "rte", "value": 0.5}]
    run.log_table(rows, "eval/simcol_3/figures.csv")
    table = pd.read_csv(tracking.client(uri).download_artifacts(run.run_id, "eval/simcol_3/figures.csv",
                                                                str(tmp_path)))
    assert table.to_dict("records") == rows
    assert tracking.client(uri).get_run(run.run_id).data.metrics == {}


@pytest.mark.parametrize("name", ["endoflow", "endoflow-latent-bank"])
def test_every_experiment_opens_on_a_view_of_its_own(tmp_path: Path, name: str):
    params = Params()
    experiment_id = tracking.ensure_experiment(params, tmp_path, name)
    tags = tracking.client(tracking.tracking_uri(params, tmp_path)).get_experiment(experiment_id).tags
    assert json.loads(tags[tracking.RUNS_VIEW_TAG])["selectedColumns"] == [tracking.SOURCE_COLUMN]
