"""The evaluation's and training's figures (endoflow/evaluation/plots.py): every text, colour-bar labels
included, stays clear of the other panels, whatever width the tick labels take; every depth panel has a colour
bar in cm."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.figure import Figure

from endoflow.evaluation import plots

SIZE = 32


def depth_example(index: int) -> dict:
    """A frame whose depth spans 2 to 15 cm (colour-bar ticks of four characters, ``12.5``) and a prediction at
    another scale."""
    v, u = np.mgrid[0:SIZE, 0:SIZE]
    gt = 2.0 + 0.8 * np.hypot(u - SIZE / 2, v - SIZE / 2)
    gt[:2] = 0.0  # no ground truth in the top rows
    return {"rgb": np.full((SIZE, SIZE, 3), 0.5), "gt": gt, "pred": 0.5 * gt + 0.01 * u, "label": f"S5 #{index}"}


def texts_over_other_panels(figure: Figure) -> list[tuple[str, str]]:
    """(text, panel title) of each axis label or title drawn over a panel other than its own axes."""
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    overlaps = []
    for axes in figure.axes:
        for text in (axes.title, axes.xaxis.label, axes.yaxis.label):
            if not text.get_text():
                continue
            box = text.get_window_extent(renderer)
            overlaps += [(text.get_text(), other.get_title()) for other in figure.axes
                         if other is not axes and not hasattr(other, "_colorbar")
                         and box.overlaps(other.get_window_extent(renderer))]
    return overlaps


@pytest.mark.parametrize("rows", [1, 3])
def test_the_depth_examples_colour_bar_labels_stay_clear_of_the_next_panel(rows: int):
    figure = plots.depth_examples_figure("simcol_3: depth examples", [depth_example(i) for i in range(rows)])
    try:
        assert texts_over_other_panels(figure) == []
        labels = [axes.get_ylabel() for axes in figure.axes if hasattr(axes, "_colorbar")]
        assert labels == ["depth (cm)", "|error| (cm)"] * rows
    finally:
        plt.close(figure)


def test_the_training_curves_name_their_units():
    history = [{"epoch": e, "train_loss": 1 / e, "val_abs_rel": 0.3 / e, "val_rmse": 2 / e, "lr": 1e-4}
               for e in (1, 2, 3)]
    figure = plots.training_curves_figure(history, ["train_loss", "val_abs_rel", "val_rmse", "lr"])
    try:
        assert [axes.get_ylabel() for axes in figure.axes] == ["training loss", "val Abs Rel", "val RMSE (cm)",
                                                               "learning rate"]
        assert texts_over_other_panels(figure) == []
    finally:
        plt.close(figure)
