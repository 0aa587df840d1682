"""Evaluation figures as plain-text tables: the summary the evaluate stage prints for one test set
(:func:`format_evaluation`), and the per-protocol tables of the model beside its baselines that
:mod:`endoflow.report` builds from the same layout for many runs.

A light module (no torch, no pandas): the report imports it.
"""

from __future__ import annotations

from typing import Any, Iterable, Optional

PAPER_COLUMNS = (("abs_rel", "Abs Rel"), ("sq_rel", "Sq Rel"), ("rmse", "RMSE"), ("rmse_log", "RMSE log"),
                 ("l1", "L1"), ("a1", "δ<1.25"), ("a2", "δ<1.25²"), ("a3", "δ<1.25³"), ("ratio", "Scale"),
                 ("near_ratio", "near GT/pred"), ("far_ratio", "far GT/pred"))
SIMCOL_DEPTH_COLUMNS = (("l1", "L1 (cm)"), ("rel", "Rel (%)"), ("rmse", "RMSE (cm)"))
SIMCOL_POSE_COLUMNS = (("ate", "ATE (cm)"), ("ate_local", "ATE local (cm)"), ("rte", "RTE (cm)"),
                       ("rot", "ROT (°)"))
ENDOSLAM_POSE_COLUMNS = (("ate", "ATE (cm)"), ("rpe_trans", "RPE trans (cm)"), ("rpe_rot", "RPE rot (°)"))
MOTION_COLUMNS = (("step_corr", "step corr"), ("forward_corr", "forward corr"), ("rotation_corr", "rotation corr"),
                  ("step_spread", "step spread"), ("direction_deg", "direction (°)"))
SCALE_COLUMNS = (("path_over_depth", "path / depth scale"), ("depth_drift", "depth scale drift"))
BASELINE_LABELS = {"constant_depth": "baseline: constant depth", "mean_depth_map": "baseline: mean depth map",
                   "constant_velocity": "baseline: constant velocity"}
# a run's own methods, a row each per run: (method, suffix of the run's label)
RUN_METHODS = (("model", ""), ("refined", ", path refined"))
# (title, protocol key of the evaluation JSON, columns), in the order the tables are shown
PROTOCOL_TABLES = (
    ("Depth, paper protocol (per-image median scaling, capped at 20 cm)", "depth_paper", PAPER_COLUMNS),
    ("Depth, SimCol3D challenge protocol (one scale per sequence)", "depth_simcol", SIMCOL_DEPTH_COLUMNS),
    ("Pose, SimCol3D challenge protocol (medians)", "pose_simcol", SIMCOL_POSE_COLUMNS),
    ("Pose, EndoSLAM protocol (ATE RMSE, RPE means)", "pose_endoslam", ENDOSLAM_POSE_COLUMNS),
    ("Motion: does the path follow the camera's changes? (correlations and spread: 1 is best; per sequence, "
     "averaged)", "pose_motion", MOTION_COLUMNS),
    ("Scale: do depth and path share one scale along a sequence? (1 is best; per sequence, averaged)", "scale",
     SCALE_COLUMNS),
)


def markdown_table(headers: list[str], rows: list[list[str]]) -> str:
    """A Markdown table with its columns padded to one width, so it also reads well as plain text."""
    widths = [max(3, *(len(cell) for cell in column)) for column in zip(headers, *rows)]

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(cell.ljust(width) for cell, width in zip(cells, widths)) + " |"

    return "\n".join([line(headers), line(["-" * width for width in widths])] + [line(row) for row in rows])


def number_cell(value: Any) -> str:
    """A figure as a table cell: four decimals, or a dash where there is none."""
    return f"{value:.4f}" if isinstance(value, (int, float)) else "–"


def protocol_table(labelled: Iterable[tuple[str, Optional[dict]]], columns: tuple[tuple[str, str], ...],
                   label_header: str = "run") -> Optional[str]:
    """One protocol's table from ``(label, {method: figures} or None)`` per run: every run's model (and its refined
    path, where it has one), then the first run's baselines; ``None`` when no run has this protocol."""
    rows = []
    baselines: dict[str, dict] = {}
    own = dict(RUN_METHODS)
    for label, methods in labelled:
        if not methods:
            continue
        rows += [[label + suffix] + [number_cell(methods[method].get(key)) for key, _ in columns]
                 for method, suffix in RUN_METHODS if method in methods]
        for method, values in methods.items():
            if method not in own:
                baselines.setdefault(method, values)
    if not rows:
        return None
    rows += [[BASELINE_LABELS.get(m, m)] + [number_cell(v.get(key)) for key, _ in columns]
             for m, v in baselines.items()]
    return markdown_table([label_header] + [title for _, title in columns], rows)


def format_evaluation(result: dict) -> str:
    """Plain-text summary of one test set's evaluation (the dict ``evaluate_test_set`` returns and writes):
    what was evaluated, then per protocol a table of the model beside its baselines."""
    name = result.get("test_set", "?")
    counts = [f"{result[key]} {noun}" for key, noun in
              (("sequences", "sequences"), ("frames", "frames"), ("depth_frames", "frames with GT depth"))
              if key in result]
    speed = f", {result['frames_per_second']:.1f} frames/s" if "frames_per_second" in result else ""
    parts = [f"Test set {name} ({result.get('dataset', '?')}): {', '.join(counts)}{speed}"]
    for title, protocol, columns in PROTOCOL_TABLES:
        table = protocol_table([("model", result.get(protocol))], columns, label_header="method")
        if table:
            parts.append(f"{title}\n{table}")
    if len(parts) == 1:
        parts.append("No depth or pose metrics: the test set has neither GT depth nor consecutive GT poses.")
    return "\n\n".join(parts) + "\n"
