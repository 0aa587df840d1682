"""The scores of one test set as one long table, and what the evaluation writes from it.

Every figure is a row of :data:`SCORE_COLUMNS`: ``sequence``, ``frame`` (``<NA>`` for a figure of a whole
sequence), ``method``, ``protocol`` (one of :data:`~endoflow.evaluation.results.PROTOCOLS`), ``metric`` and
``value``. The protocols aggregate as they are defined: the paper's depth errors are per image and average over
all images of the test set; the challenge's and EndoSLAM's figures are per sequence and average over the
sequences (the challenge's per-frame errors are rows too, for the per-frame table).
"""

from __future__ import annotations

from typing import Iterable, Mapping, Optional

import numpy as np
import pandas as pd

from endoflow.evaluation import metrics
from endoflow.evaluation.baselines import DEPTH_BASELINES, POSE_BASELINES

DEPTH_METHODS = ("model", *DEPTH_BASELINES)
POSE_METHODS = ("model", "refined", *POSE_BASELINES)  # refined: the model's path refined (params refine.*)
SCORE_COLUMNS = ("sequence", "frame", "method", "protocol", "metric", "value")
# each protocol's methods and figures, in the order evaluation.json lists them
PROTOCOL_FIGURES = {
    "depth_paper": (DEPTH_METHODS, metrics.PAPER_DEPTH_KEYS),
    "depth_simcol": (DEPTH_METHODS, metrics.SIMCOL_DEPTH_KEYS),
    "pose_simcol": (POSE_METHODS, metrics.SIMCOL_POSE_KEYS),
    "pose_endoslam": (POSE_METHODS, metrics.ENDOSLAM_POSE_KEYS),
    "pose_motion": (POSE_METHODS, metrics.MOTION_KEYS),
    "scale": (("model", "refined"), metrics.SCALE_KEYS),
}
AVERAGED_OVER_IMAGES = ("depth_paper",)
# the columns of per_frame.csv and per_sequence.csv: (methods, (protocol, metric, column prefix)...), in order;
# a column is named <prefix>_<method>
PER_FRAME_COLUMNS = ((DEPTH_METHODS, (("depth_paper", "abs_rel", "abs_rel"), ("depth_paper", "rmse", "rmse"),
                                      ("depth_simcol", "l1", "simcol_l1"))),
                     (POSE_METHODS, (("pose_simcol", "rte", "rte"), ("pose_simcol", "rot", "rot"))))
PER_SEQUENCE_COLUMNS = ((DEPTH_METHODS, (("depth_simcol", "l1", "simcol_l1"),)),
                        (POSE_METHODS, (("pose_simcol", "rte", "rte"), ("pose_simcol", "rot", "rot"),
                                        ("pose_motion", "step_corr", "step_corr"))))


def score_rows(sequence: str, frame: Optional[int], method: str, protocol: str,
               figures: Mapping[str, float]) -> list[dict]:
    """Rows of the scores table for ``figures`` of one frame (``frame=None``: of the whole sequence)."""
    return [{"sequence": sequence, "frame": frame, "method": method, "protocol": protocol, "metric": metric,
             "value": float(value)} for metric, value in figures.items()]


def scores_table(rows: Iterable[dict]) -> pd.DataFrame:
    """The long table of :data:`SCORE_COLUMNS` from :func:`score_rows`' rows."""
    return pd.DataFrame(list(rows), columns=list(SCORE_COLUMNS)).astype({"frame": "Int64", "value": "float64"})


def protocol_summary(scores: pd.DataFrame) -> dict[str, dict[str, dict[str, float]]]:
    """``{protocol: {method: {metric: mean}}}`` of every protocol and method with scores: per-image figures
    averaged over the images, per-sequence figures over the sequences."""
    summary: dict = {}
    for protocol, (methods, keys) in PROTOCOL_FIGURES.items():
        rows = scores[scores["protocol"] == protocol]
        per_image = protocol in AVERAGED_OVER_IMAGES
        rows = rows[rows["frame"].notna() if per_image else rows["frame"].isna()]
        figures = {method: _means(rows[rows["method"] == method], keys) for method in methods
                   if (rows["method"] == method).any()}
        if figures:
            summary[protocol] = figures
    return summary


def _means(rows: pd.DataFrame, keys: tuple[str, ...]) -> dict[str, float]:
    return {key: float(np.mean(rows.loc[rows["metric"] == key, "value"].to_numpy())) for key in keys}


def per_frame_table(frames: pd.DataFrame, scores: pd.DataFrame) -> pd.DataFrame:
    """``frames`` (``sequence``, ``frame``: every evaluated frame, in order) with the per-frame figures of
    :data:`PER_FRAME_COLUMNS` beside them and a leading ``index``."""
    rows = scores[scores["frame"].notna()].astype({"frame": "int64"})
    table = _with_columns(frames, rows, ["sequence", "frame"], PER_FRAME_COLUMNS)
    table.insert(0, "index", np.arange(len(table)))
    return table


def per_sequence_table(sequences: pd.DataFrame, scores: pd.DataFrame) -> pd.DataFrame:
    """``sequences`` (``sequence`` first) with the per-sequence figures of :data:`PER_SEQUENCE_COLUMNS`."""
    return _with_columns(sequences, scores[scores["frame"].isna()], ["sequence"], PER_SEQUENCE_COLUMNS)


def _with_columns(table: pd.DataFrame, rows: pd.DataFrame, keys: list[str], layout: tuple) -> pd.DataFrame:
    """``table`` with every column ``layout`` names (the figures of ``rows``, joined on ``keys``; empty where
    ``rows`` has none)."""
    names = {(protocol, metric, method): f"{prefix}_{method}"
             for methods, figures in layout for method in methods for protocol, metric, prefix in figures}
    column = pd.Series([names.get(key) for key in zip(rows["protocol"], rows["metric"], rows["method"])],
                       index=rows.index, dtype=object)
    rows = rows.assign(column=column).dropna(subset=["column"])
    wide = rows.pivot(index=keys, columns="column", values="value") if not rows.empty else pd.DataFrame()
    # every column of the layout, empty where no method has that figure: the tables DVC charts keep one schema
    wide = wide.reindex(columns=list(names.values())).reset_index() if not rows.empty else \
        pd.DataFrame(columns=[*keys, *names.values()])
    wide.columns.name = None
    return table.merge(wide.astype({name: "float64" for name in names.values()}), how="left", on=keys)
