"""`endoflow report`: Markdown tables from the workspace's evaluation JSON and from `dvc exp show --json`."""

from __future__ import annotations

import json
from pathlib import Path

from endoflow.cli import main
from endoflow.report import experiment_results, format_report, workspace_results


def evaluation(abs_rel: float, rte: float) -> dict:
    return {
        "test_set": "simcol_12",
        "depth_paper": {"model": {"abs_rel": abs_rel, "sq_rel": 0.1, "rmse": 1.0, "rmse_log": 0.2, "l1": 0.5,
                                  "a1": 0.8, "a2": 0.9, "a3": 0.95},
                        "constant_depth": {"abs_rel": 0.5, "a1": 0.3}},
        "depth_simcol": {"model": {"l1": 0.4, "rel": 9.0, "rmse": 0.7}},
        "pose_simcol": {"model": {"ate": 2.0, "rte": rte, "rot": 1.5}, "constant_velocity": {"rte": 0.9}},
    }


def exp_show(experiments: dict[str, tuple[bool, bool, float]]) -> list[dict]:
    """The shape `dvc exp show --json` prints: baseline commits, each with ranges of experiment revisions."""
    def state(rev: str, name: str | None, bank: bool, vae: bool, abs_rel: float | None) -> dict:
        metrics = {} if abs_rel is None else {"metrics/eval/simcol_12.json": {"data": evaluation(abs_rel, 0.3)}}
        return {"rev": rev, "name": name, "error": None, "experiments": None,
                "data": {"rev": rev, "params": {"params.yaml": {"data": {"model": {"latent_bank": bank,
                                                                                   "pose_vae": vae}}}},
                         "metrics": metrics}}

    head = state("abc1234def", "main", True, True, None)
    head["experiments"] = [{"name": name, "executor": None, "revs": [state(f"{i:07d}", name, *flags)]}
                           for i, (name, flags) in enumerate(experiments.items())]
    return [state("workspace", None, True, True, 0.11), head]


def test_experiments_become_labelled_runs_and_the_workspace_row_is_not_duplicated():
    runs = experiment_results(exp_show({"no-bank": (False, True, 0.2), "no-vae": (True, False, 0.15)}),
                              "metrics/eval")
    assert [r.label for r in runs] == ["no-bank (bank off, VAE on)", "no-vae (bank on, VAE off)"]
    assert runs[0].test_sets["simcol_12"]["depth_paper"]["model"]["abs_rel"] == 0.2


def test_report_has_a_table_per_protocol_with_baselines_and_an_ablation_summary(tmp_path: Path):
    (tmp_path / "simcol_12.json").write_text(json.dumps(evaluation(0.1234, 0.25)))
    runs = [workspace_results(tmp_path, {"model": {"latent_bank": True, "pose_vae": True}}),
            *experiment_results(exp_show({"no-bank": (False, True, 0.2)}), "metrics/eval")]
    report = format_report(runs)
    assert "## simcol_12" in report
    assert "### Depth, paper protocol" in report and "### Depth, SimCol3D challenge protocol" in report
    assert "| workspace (bank on, VAE on) | 0.1234 | 0.1000 |" in report
    assert "| baseline: constant depth | 0.5000 | – |" in report
    assert "| baseline: constant velocity | – | 0.9000 | – |" in report
    assert "| no-bank (bank off, VAE on) | 0.2000 | 0.3000 |" in report.split("## Ablation summary")[1]
    assert "EndoSLAM protocol" not in report  # absent protocols get no empty table


def test_cli_report_on_a_workspace_without_metrics(tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["report", "--no-experiments"]) == 0
    assert "No evaluation metrics found" in capsys.readouterr().out
