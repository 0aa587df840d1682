"""Where an evaluation's figures live, and which of them are its headline.

The ``evaluate`` stage writes every figure (each protocol, method and metric) to
``<eval.predictions>/<test set>/evaluation.json``, and only the headline, under the test set's name
(``{"simcol_12": {"abs_rel": ..., "rte": ..., "rot": ...}}``), to ``<eval.metrics>/<test set>.json``, the file
DVC reads as metrics: ``dvc exp show`` then has three columns per test set (``simcol_12.abs_rel``) instead of
hundreds, and ``endoflow report`` reads the full figures. MLflow gets both (the headline as
``<test set>/<metric>``, a column that fits the runs table). A light module: the report imports it without torch.
"""

from __future__ import annotations

from pathlib import Path

EVALUATION_FILE = "evaluation.json"
# (name, protocol, method, metric) of each headline figure: the paper's depth metric and the SimCol3D
# challenge's pose metrics, of the model
HEADLINE = (("abs_rel", "depth_paper", "model", "abs_rel"),
            ("rte", "pose_simcol", "model", "rte"),
            ("rot", "pose_simcol", "model", "rot"))


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
