"""PNG figures for evaluation and training (matplotlib, Agg backend: no display, no network to view).

Every function returns a closed-over ``Figure``; callers save it (atomically) or log it to MLflow and then
close it with :func:`matplotlib.pyplot.close`.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

# y labels of the training history's columns (``plots/train/history.csv``)
CURVE_LABELS = {"train_loss": "training loss", "val_abs_rel": "val Abs Rel", "val_rmse": "val RMSE (cm)",
                "val_photometric": "val photometric error",
                "lr": "learning rate"}


def trajectory_figure(title: str, gt_positions: np.ndarray, predicted: Mapping[str, np.ndarray]) -> Figure:
    """Top (x-z) and side (z-y) views of ``N x 3`` camera positions in cm, GT against each prediction.

    The OpenCV world convention has y pointing down, so the side view plots ``-y`` upwards.
    """
    figure, (top, side) = plt.subplots(1, 2, figsize=(10, 4.5))
    for name, positions in {"GT": gt_positions, **predicted}.items():
        style = {"color": "black", "linewidth": 2.0} if name == "GT" else {"linewidth": 1.2}
        top.plot(positions[:, 0], positions[:, 2], label=name, **style)
        side.plot(positions[:, 2], -positions[:, 1], label=name, **style)
    top.scatter(gt_positions[:1, 0], gt_positions[:1, 2], color="black", marker="o", zorder=3)
    side.scatter(gt_positions[:1, 2], -gt_positions[:1, 1], color="black", marker="o", zorder=3)
    top.set(title="top view", xlabel="x (cm)", ylabel="z (cm)")
    side.set(title="side view", xlabel="z (cm)", ylabel="-y (cm)")
    for axis in (top, side):
        axis.set_aspect("equal", adjustable="datalim")
        axis.grid(alpha=0.3)
    top.legend(fontsize=8)
    figure.suptitle(title)
    figure.tight_layout()
    return figure


def depth_examples_figure(title: str, examples: Sequence[Mapping[str, object]]) -> Figure:
    """One row per example: RGB, GT depth, predicted depth (median-scaled) and its absolute error (cm).

    Each example maps ``rgb`` (``H x W x 3`` in [0, 1]), ``gt`` and ``pred`` (``H x W`` cm) and ``label``.
    GT and prediction share one colour scale per row, with one colour bar; pixels without GT are shown black in
    the error map. Constrained layout keeps the colour bars' labels clear of the next panel.
    """
    rows = max(len(examples), 1)
    figure, axes = plt.subplots(rows, 4, figsize=(13, 3 * rows), squeeze=False, layout="constrained")
    for row, example in zip(axes, examples):
        gt = np.asarray(example["gt"], dtype=np.float64)
        pred = np.asarray(example["pred"], dtype=np.float64)
        valid = gt > 0
        scaled = pred * (np.median(gt[valid]) / np.median(pred[valid]) if valid.any() else 1.0)
        vmax = float(np.percentile(gt[valid], 99)) if valid.any() else float(scaled.max())
        error = np.where(valid, np.abs(scaled - gt), np.nan)
        row[0].imshow(np.clip(example["rgb"], 0, 1))
        row[1].imshow(np.where(valid, gt, np.nan), cmap="magma_r", vmin=0, vmax=vmax)
        image = row[2].imshow(scaled, cmap="magma_r", vmin=0, vmax=vmax)
        figure.colorbar(image, ax=list(row[1:3]), shrink=0.9, label="depth (cm)")
        error_image = row[3].imshow(error, cmap="inferno")
        figure.colorbar(error_image, ax=row[3], shrink=0.9, label="|error| (cm)")
        row[3].set_facecolor("black")
        for axis, name in zip(row, ("RGB", "GT depth", "prediction (median-scaled)", "absolute error")):
            axis.set_title(f"{example['label']}: {name}" if name == "RGB" else name, fontsize=9)
            axis.axis("off")
    figure.suptitle(title)
    return figure


def error_curves_figure(title: str, curves: Mapping[str, Mapping[str, np.ndarray]]) -> Figure:
    """One panel per metric (``{metric: {method: per-frame values}}``), values against frame index."""
    panels = max(len(curves), 1)
    figure, axes = plt.subplots(panels, 1, figsize=(10, 2.6 * panels), squeeze=False)
    for axis, (metric, methods) in zip(axes[:, 0], curves.items()):
        for method, values in methods.items():
            axis.plot(np.arange(len(values)), values, label=method, linewidth=1.0)
        axis.set(ylabel=metric)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    axes[-1, 0].set_xlabel("frame index in the test set")
    figure.suptitle(title)
    figure.tight_layout()
    return figure


def training_curves_figure(history: Sequence[Mapping[str, float]], keys: Sequence[str]) -> Figure:
    """Per-epoch curves of ``keys`` from the training history (one panel each), labelled with their units."""
    figure, axes = plt.subplots(len(keys), 1, figsize=(7, 2.5 * len(keys)), squeeze=False)
    epochs = [record["epoch"] for record in history]
    for axis, key in zip(axes[:, 0], keys):
        axis.plot(epochs, [record.get(key, np.nan) for record in history], marker="o")
        axis.set(ylabel=CURVE_LABELS.get(key, key))
        axis.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("epoch")
    figure.tight_layout()
    return figure
