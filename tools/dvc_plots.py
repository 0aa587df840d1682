"""Write dvc.yaml's charts from params.yaml: one per table of every test set and reconstructed sequence it names.

DVC cannot loop in its top-level plots, so each test set's two charts (depth and pose error per frame) and each
reconstructed sequence's (the path's position error per frame) are entries of their own. ``python -m
tools.dvc_plots`` (``make dvc-plots``, which ``make repro`` runs) rewrites the block from ``plots:`` to the end of
dvc.yaml for the test sets and sequences of ``params.yaml``, so that a test set added to the params is charted and
one removed leaves no chart of a file the pipeline no longer writes. Everything above the block stays as it is.
``tests/test_dvc_plots.py`` fails while the committed dvc.yaml's charts are not those of the committed params.yaml.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from endoflow.config import Params, load_params
from endoflow.evaluation.evaluate import DEPTH_METHODS, POSE_METHODS
from endoflow.io import write_text
from endoflow.reconstruction.measure import PATH_ROWS

PROJECT = Path(__file__).resolve().parents[1]
COMMAND = "make dvc-plots"  # what a failing check tells the user to run
BLOCK_START = "plots:\n"
TRAINING_COLUMNS = ("train_loss", "val_abs_rel", "val_rmse", "val_photometric")
WIDTH = 118  # the longest line written; a flow list longer than that continues under its first column


def charts_block(params: Params) -> str:
    """dvc.yaml's top-level ``plots:`` block: the training curves, then two charts per test set of ``params``, then
    one per reconstructed sequence (the order of the page: training, evaluation, reconstruction)."""
    lines = [BLOCK_START.rstrip("\n")]
    lines += chart("training curves", "epoch", "${train.plots}/history.csv", TRAINING_COLUMNS,
                   title="training: loss and validation error per epoch")
    for name in params.eval.test_sets:
        table = f"${{eval.predictions}}/{name}/per_frame.csv"
        lines += chart(f"{name} depth error per frame", "index", table, [f"abs_rel_{m}" for m in DEPTH_METHODS],
                       y_label="Abs Rel (paper protocol)")
        lines += chart(f"{name} pose error per frame", "index", table, [f"rte_{m}" for m in POSE_METHODS],
                       y_label="RTE (cm)")
    for name in params.reconstruct.sequences:
        table = f"${{reconstruct.out}}/{name}/path_errors.csv"
        lines += chart(f"{name} camera path error", "frame", table, PATH_ROWS,
                       y_label="position error after alignment (cm)")
    return "\n".join(lines) + "\n"


def chart(name: str, x: str, table: str, columns: Sequence[str], title: str | None = None,
          y_label: str | None = None) -> list[str]:
    """One top-level chart: ``columns`` of ``table`` against ``x``."""
    lines = [f"  - {name}:", f"      x: {x}", "      y:", *wrapped(f"        {table}: [", columns)]
    if title is not None:
        lines.append(f'      title: "{title}"')
    if y_label is not None:
        lines.append(f"      y_label: {y_label}")
    return lines


def wrapped(head: str, columns: Sequence[str]) -> list[str]:
    """``head`` followed by the flow list of ``columns``, in lines of at most :data:`WIDTH` characters."""
    items = [f"{column}," for column in columns[:-1]] + [f"{columns[-1]}]"]
    lines = [head + items[0]]
    for item in items[1:]:
        if len(lines[-1]) + 1 + len(item) > WIDTH:
            lines.append(" " * len(head) + item)
        else:
            lines[-1] += " " + item
    return lines


def rewrite_plots(text: str, params: Params) -> str:
    """``text`` (dvc.yaml) with its top-level ``plots:`` block written for ``params``.

    Raises:
        ValueError: dvc.yaml has no such block, or another top-level key follows it (it would be lost).
    """
    start = text.find(f"\n{BLOCK_START}")
    if start < 0:
        raise ValueError(f"dvc.yaml has no top-level block starting with {BLOCK_START.strip()!r}")
    after = text[start + 1 + len(BLOCK_START):].splitlines()
    following = [line for line in after if line[:1] not in ("", " ", "#")]
    if following:
        raise ValueError(f"dvc.yaml: the top-level plots block must be the file's last; {following[0]!r} follows it")
    return text[:start + 1] + charts_block(params)


def main() -> None:
    dvc_yaml = PROJECT / "dvc.yaml"
    text = dvc_yaml.read_text()
    try:
        new = rewrite_plots(text, load_params(PROJECT / "params.yaml"))
    except ValueError as exc:  # bad params (ConfigError) or a dvc.yaml it cannot rewrite: the message names the file
        raise SystemExit(f"make dvc-plots: {exc}") from None
    if new == text:
        print("dvc.yaml: the charts are those of params.yaml's test sets and sequences already")
        return
    write_text(dvc_yaml, new)
    print("dvc.yaml: charts written for params.yaml's test sets and reconstructed sequences")


if __name__ == "__main__":
    main()
