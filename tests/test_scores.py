"""The scores of a test set as one long table: the summary, per_frame.csv and per_sequence.csv derive from it."""

from __future__ import annotations

from math import nan

import pandas as pd
import pytest

from endoflow.evaluation.scores import (
    DEPTH_METHODS,
    POSE_METHODS,
    per_frame_table,
    per_sequence_table,
    protocol_summary,
    score_rows,
    scores_table,
)


def paper(abs_rel: float) -> dict[str, float]:
    return {"abs_rel": abs_rel, "sq_rel": 0.0, "rmse": 2 * abs_rel, "rmse_log": 0.0, "l1": 0.0, "a1": 1.0,
            "a2": 1.0, "a3": 1.0, "ratio": 1.0, "near_ratio": 1.0, "far_ratio": 1.0}


def simcol_depth(l1: float) -> dict[str, float]:
    return {"l1": l1, "rel": 0.0, "rmse": 0.0}


@pytest.fixture
def scores() -> pd.DataFrame:
    """Sequence A: three images with GT depth, no pose; sequence B: one image and one posed step."""
    rows = [row for frame, value in ((1, 0.1), (2, 0.2), (3, 0.3))
            for row in score_rows("A", frame, "model", "depth_paper", paper(value))]
    rows += score_rows("A", None, "model", "depth_simcol", simcol_depth(1.0))
    rows += score_rows("B", 5, "model", "depth_paper", paper(0.6))
    rows += score_rows("B", None, "model", "depth_simcol", simcol_depth(3.0))
    rows += score_rows("B", 6, "constant_velocity", "pose_simcol", {"rte": 0.5, "rot": 2.0})
    rows += score_rows("B", None, "constant_velocity", "pose_simcol", {"ate": 1, "ate_local": 1, "rte": 0.5, "rot": 2})
    return scores_table(rows)


def test_paper_depth_averages_over_images_the_other_protocols_over_sequences(scores: pd.DataFrame) -> None:
    summary = protocol_summary(scores)
    assert summary["depth_paper"]["model"]["abs_rel"] == pytest.approx(0.3)  # (0.1 + 0.2 + 0.3 + 0.6) / 4
    assert summary["depth_simcol"]["model"]["l1"] == pytest.approx(2.0)  # (1 + 3) / 2, not weighted by images
    assert list(summary) == ["depth_paper", "depth_simcol", "pose_simcol"]  # no EndoSLAM rows, no entry
    assert list(summary["pose_simcol"]) == ["constant_velocity"]


def test_the_tables_list_every_frame_and_sequence_with_their_figures_as_columns(scores: pd.DataFrame) -> None:
    frames = pd.DataFrame({"sequence": ["A"] * 4 + ["B"] * 3, "frame": [0, 1, 2, 3, 4, 5, 6]})
    table = per_frame_table(frames, scores)
    # one schema whatever the methods scored: every column of the layout, empty where nothing was scored
    assert list(table.columns) == ["index", "sequence", "frame",
                                   *(f"{figure}_{method}" for method in DEPTH_METHODS
                                     for figure in ("abs_rel", "rmse", "simcol_l1")),
                                   *(f"{figure}_{method}" for method in POSE_METHODS for figure in ("rte", "rot"))]
    assert table["rte_model"].isna().all() and table["simcol_l1_model"].isna().all()
    assert table["abs_rel_model"].tolist() == pytest.approx([nan, 0.1, 0.2, 0.3, nan, 0.6, nan], nan_ok=True)
    assert table["rte_constant_velocity"].notna().tolist() == [False] * 6 + [True]
    sequences = per_sequence_table(pd.DataFrame({"sequence": ["A", "B"], "group": ["g", "g"], "frames": [4, 3]}),
                                   scores)
    assert list(sequences.columns)[:3] == ["sequence", "group", "frames"]
    assert {"simcol_l1_model", "rte_constant_velocity", "rot_constant_velocity", "step_corr_refined"} <= \
        set(sequences.columns)
    assert sequences["simcol_l1_model"].tolist() == [1.0, 3.0]
