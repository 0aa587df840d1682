"""Where an evaluation's figures live, and which of them are its headline.

The ``evaluate`` stage writes every figure (each protocol, method and metric) to
``<eval.predictions>/<test set>/evaluation.json`` (what ``endoflow report`` reads), and only the headline to
``<eval.metrics>/<test set>.json``, the file DVC reads as metrics: ``{"eval_simcol_12": {"abs_rel": ...,
"rte_cm": ..., "rot_deg": ...}}``, three columns per test set in ``dvc exp show``, named apart from every other
stage's (see docs/outputs.md). A light module: the report imports it without torch.
"""

from __future__ import annotations

from pathlib import Path

EVALUATION_FILE = "evaluation.json"
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


def dvc_metrics(test_set: str, result: dict) -> dict[str, dict[str, float]]:
    """The content of ``<eval.metrics>/<test set>.json``: the headline under ``eval_<test set>``, a key no other
    metrics file has (a reconstructed sequence may share the test set's name)."""
    return {f"eval_{test_set}": headline_metrics(result)}
