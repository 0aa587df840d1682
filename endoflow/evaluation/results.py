"""Where an evaluation's figures live, and which of them are its headline.

The ``evaluate`` stage writes every figure (each protocol, method and metric) to
``<eval.predictions>/<test set>/evaluation.json`` (what ``endoflow report`` reads), and only the headline to
``<eval.metrics>/<test set>.json``, the file DVC reads as metrics: ``{"test_simcol_12": {"abs_rel": ...,
"rte_cm": ..., "rot_deg": ...}}``, three columns per test set in ``dvc exp show``, named apart from every other
stage's (see docs/outputs.md). MLflow gets the headline as metrics (``test/simcol_12/abs_rel``, columns of its
runs table; on a run's page their one-point charts sort after the training's curves) and every figure as one
table (:func:`figure_rows`), not as hundreds of one-point charts. A light module: the report imports it without
torch.
"""

from __future__ import annotations

from pathlib import Path

EVALUATION_FILE = "evaluation.json"
# the blocks of an evaluation result that hold {method: {metric: value}}
PROTOCOLS = ("depth_paper", "depth_simcol", "pose_simcol", "pose_endoslam", "pose_motion", "scale")
# (name with its unit, protocol, method, metric) of each headline figure: the paper's depth metric (a ratio) and
# the SimCol3D challenge's pose metrics (medians, cm and degrees), of the model
HEADLINE = (("abs_rel", "depth_paper", "model", "abs_rel"),
            ("rte_cm", "pose_simcol", "model", "rte"),
            ("rot_deg", "pose_simcol", "model", "rot"))


def evaluation_path(predictions_dir: str | Path, test_set: str) -> Path:
    """The full evaluation JSON of ``test_set`` under the ``eval.predictions`` folder."""
    return Path(predictions_dir) / test_set / EVALUATION_FILE


def headline_metrics(result: dict) -> dict[str, float]:
    """The headline figures of an evaluation result that has them (a test set without GT depth has no Abs Rel)."""
    found = {}
    for name, protocol, method, metric in HEADLINE:
        value = result.get(protocol, {}).get(method, {}).get(metric)
        if isinstance(value, (int, float)):
            found[name] = float(value)
    return found


def mlflow_metrics(test_set: str, result: dict) -> dict[str, float]:
    """The headline as MLflow metrics: ``test/<test set>/<name>``."""
    return {f"test/{test_set}/{name}": value for name, value in headline_metrics(result).items()}


def figure_rows(result: dict) -> list[dict]:
    """Every figure of an evaluation result, one row each: ``protocol``, ``method``, ``metric``, ``value``."""
    return [{"protocol": protocol, "method": method, "metric": metric, "value": value}
            for protocol in PROTOCOLS if protocol in result
            for method, figures in result[protocol].items() for metric, value in figures.items()]


def dvc_metrics(test_set: str, result: dict) -> dict[str, dict[str, float]]:
    """The content of ``<eval.metrics>/<test set>.json``: the headline under ``test_<test set>``, a key no other
    metrics file has (a reconstructed sequence may share the test set's name)."""
    return {f"test_{test_set}": headline_metrics(result)}
