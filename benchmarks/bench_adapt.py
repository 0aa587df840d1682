"""What `endoflow adapt` costs and gives on one video: the time and CPU time of the adaptation, the held-out
photometric error before and after, and the depth of held-out frames drawn before and after.

    python benchmarks/bench_adapt.py VIDEO --model models/endoflow.pt [--crop X,Y,W,H] [--steps 300]
                                     [--adapted ADAPTED.pt] [--also LABEL=MODEL ...] [--figure depth.png]
                                     [--frames 4] [--rgb]

Without ``--adapted`` it adapts ``--model`` to ``VIDEO`` as `endoflow adapt` does (into a temporary file) and
prints steps per second and the CPU seconds this process used; with it, it only compares the two models.
``--also`` adds models to compare (a model trained with the video in its training data, say), each under its label.
The figure has one row per model, the depth of evenly spaced held-out frames in cm at the model's scale (black outside
the field of view), one colour scale per row; ``--rgb`` adds the frames above (leave them out for footage whose
licence does not let you publish it).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from endoflow.data.crop import Crop  # noqa: E402
from endoflow.devices import use_cpu_threads  # noqa: E402
from endoflow.models.endoflow_model import load_trained_model  # noqa: E402
from endoflow.training.adapt import (  # noqa: E402
    AdaptOptions,
    adapt,
    held_out_error,
    input_sequence,
    kept_frames,
    load_frames,
)


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def held_out_depth(model_path: Path, frames, held_out: torch.Tensor, drawn: torch.Tensor) -> tuple[np.ndarray, float]:
    """Depth (cm, ``[N, S, S]``) of the frames ``drawn`` and the photometric error over the ``held_out`` targets
    (as `endoflow adapt` measures it) of the model at ``model_path``."""
    model, _ = load_trained_model(model_path, torch.device("cpu"))
    with torch.no_grad():
        depth = model.predict_depth(frames.batch(drawn, torch.device("cpu"))["cur"])[:, 0].numpy()
    return depth, held_out_error(model, frames, held_out, torch.device("cpu"))


def depth_figure(rows: dict[str, np.ndarray], valid: np.ndarray, rgb: np.ndarray | None, labels: list[str]):
    count = len(labels)
    names = (["frame"] if rgb is not None else []) + list(rows)
    figure, axes = plt.subplots(len(names), count, figsize=(2.6 * count + 1, 2.5 * len(names)), squeeze=False,
                                layout="constrained")
    if rgb is not None:
        for axis, image, label in zip(axes[0], rgb, labels):
            axis.imshow(image)
            axis.set_title(label, fontsize=9)
    for row, (name, depth) in zip(axes[len(names) - len(rows):], rows.items()):
        shown = np.where(valid, depth, np.nan)
        vmax = float(np.nanpercentile(shown, 99))
        for axis, image, label in zip(row, shown, labels):
            drawn = axis.imshow(image, cmap="magma_r", vmin=0, vmax=vmax)
            axis.set_facecolor("black")
            axis.set_title(f"{name}: {label}", fontsize=9)
        figure.colorbar(drawn, ax=list(row), shrink=0.9, label="depth (cm, model scale)")
    for axis in axes.flat:
        axis.axis("off")
    return figure


def labelled_model(text: str) -> tuple[str, Path]:
    label, separator, path = text.partition("=")
    if not separator or not label or not path:
        raise argparse.ArgumentTypeError(f"expected LABEL=MODEL, got {text!r}")
    return label, Path(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("video", type=Path)
    parser.add_argument("--model", type=Path, default=Path("models/endoflow.pt"))
    parser.add_argument("--adapted", type=Path, help="an adapted model to compare (default: adapt now)")
    parser.add_argument("--crop", type=Crop.parse)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--figure", type=Path)
    parser.add_argument("--frames", type=int, default=4, choices=range(1, 33), metavar="1..32",
                        help="held-out frames drawn")
    parser.add_argument("--rgb", action="store_true", help="draw the frames above their depth")
    parser.add_argument("--also", nargs="+", default=[], type=labelled_model, metavar="LABEL=MODEL",
                        help="more models to compare, e.g. trained-on-clip=clip.pt")
    args = parser.parse_args()
    use_cpu_threads(args.threads)
    _, record = load_trained_model(args.model, torch.device("cpu"))
    sequence = input_sequence(args.video, None, record.params, args.crop)
    adapted = args.adapted
    if adapted is None:
        adapted = Path(tempfile.mkdtemp(prefix="endoflow-bench-adapt-")) / "adapted.pt"  # kept: it is printed
        started, cpu = time.monotonic(), cpu_seconds()
        adapt(sequence, args.model, adapted, AdaptOptions(steps=args.steps, device="cpu"))
        wall, cpu = time.monotonic() - started, cpu_seconds() - cpu
        print(f"adapted model: {adapted}")
        print(f"adaptation: {args.steps} steps in {wall:.0f} s ({args.steps / wall:.2f} steps/s), {cpu:.0f} CPU s, "
              f"{args.threads} threads, {len(sequence)} frames")
    count = len(sequence)
    kept = kept_frames(count, AdaptOptions().held_out)
    frames = load_frames(sequence, list(range(count)), record.params.data.size)
    held_out = torch.arange(kept + 1, count - 1)  # the targets `endoflow adapt` scores
    drawn = torch.linspace(kept + 1, count - 2, args.frames).round().long()
    depths = {}
    for name, path in (("default", args.model), ("adapted", adapted), *args.also):
        depths[name], error = held_out_depth(path, frames, held_out, drawn)
        print(f"{name}: held-out photometric error {error:.4f} ({path})")
    if args.figure:
        rgb = frames.rgb[drawn].permute(0, 2, 3, 1).numpy() if args.rgb else None
        figure = depth_figure(depths, frames.valid[0].numpy(), rgb, [f"frame {int(i)}" for i in drawn])
        figure.savefig(args.figure, dpi=110)
        print(f"figure: {args.figure}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
