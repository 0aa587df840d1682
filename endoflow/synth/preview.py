"""A picture of synthetic frames beside their depth maps (``docs/img/synthetic_frames.png``).

Usage: ``python -m endoflow.synth.preview OUT.png [--size 192] [--seed 0] [--real SIMCOL3D_ROOT]``; the rows
are rendered exactly as the writers render them. See docs/synthetic_data.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from endoflow.config import Params  # noqa: E402
from endoflow.data.simcol import SimColReader  # noqa: E402
from endoflow.data.scenenet import scenenet_intrinsics  # noqa: E402
from endoflow.errors import DataFormatError  # noqa: E402
from endoflow.io import save_figure  # noqa: E402
from endoflow.synth.render import MAX_DEPTH_CM, render_tube_frame  # noqa: E402
from endoflow.synth.rooms import render_room  # noqa: E402
from endoflow.synth.writers import (  # noqa: E402
    plan_jobs,
    room_sequence,
    scenenet_shape,
    simcol_intrinsics,
    tube_sequence,
    unitycam_intrinsics,
)

FRAMES = 40  # sequence length; the picture shows its first and last frame


def preview_rows(size: int, seed: int) -> list[tuple[str, list[np.ndarray], list[np.ndarray], str]]:
    """``(title, [rgb, rgb], [depth, depth], depth unit)`` per row."""
    params = Params()
    rows = []
    simcol = plan_jobs("simcol", Path("unused"), 1, FRAMES, size, seed, "cpu", params)
    endoslam = plan_jobs("endoslam", Path("unused"), 2, FRAMES, size, seed, "cpu", params)
    for job, K in [(job, simcol_intrinsics(size)) for job in simcol] + [(job, unitycam_intrinsics(size)) for job in endoslam]:
        sequence = tube_sequence(job)
        rendered = [render_tube_frame(sequence.scene, sequence.poses[f], K, size, size) for f in (0, FRAMES - 1)]
        title = f"SimCol3D {job.group} {job.name}" if job.layout == "simcol" else f"EndoSLAM UnityCam/{job.group}"
        rows.append((title, [r for r, _ in rendered], [d for _, d in rendered], "z-depth, cm"))
    job = plan_jobs("scenenet", Path("unused"), 1, 2, size, seed, "cpu", params)[0]
    room, poses = room_sequence(job)
    height, width = scenenet_shape(size)
    K = scenenet_intrinsics(height, width)
    rendered = [render_room(room, pose, K, height, width, device="cpu") for pose in poses]
    rows.append(("SceneNet-like room", [r for r, _ in rendered], [d / 100 for _, d in rendered], "ray length, m"))
    return rows


def real_simcol_row(root: Path) -> tuple[str, list[np.ndarray], list[np.ndarray], str]:
    """The first and last frame of the first sequence of the SimCol3D root ``root``, as a preview row."""
    sequence = SimColReader(root, Params().data.simcol).sequences()[0]
    frames = [sequence.frame(i) for i in (0, len(sequence) - 1)]
    title = f"real SimCol3D {sequence.group} {sequence.name}"
    return title, [f.rgb.astype(np.float32) / 255 for f in frames], [f.depth_cm for f in frames], "z-depth, cm"


def save_preview(path: Path, size: int = 192, seed: int = 0, real_simcol: Path | None = None) -> None:
    rows = ([real_simcol_row(real_simcol)] if real_simcol is not None else []) + preview_rows(size, seed)
    figure, axes = plt.subplots(len(rows), 4, figsize=(10, 2.6 * len(rows)), constrained_layout=True)
    for row, (title, images, depths, unit) in zip(axes, rows):
        top = MAX_DEPTH_CM if unit.endswith("cm") else max(float(d.max()) for d in depths)
        for k, (image, depth) in enumerate(zip(images, depths)):
            row[2 * k].imshow(np.clip(image, 0, 1))
            shown = row[2 * k + 1].imshow(depth, cmap="magma_r", vmin=0, vmax=top)
            row[2 * k].set_title(f"{title}, frame {0 if k == 0 else 'last'}", fontsize=8)
            row[2 * k + 1].set_title(f"depth ({unit})", fontsize=8)
        figure.colorbar(shown, ax=row[3], fraction=0.046)
        for axis in row:
            axis.set_axis_off()
    save_figure(path, figure, dpi=90)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--size", type=int, default=192)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--real", type=Path, default=None, help="a SimCol3D root to show beside the built-in data")
    args = parser.parse_args()
    try:
        save_preview(args.out, args.size, args.seed, args.real)
    except DataFormatError as exc:
        parser.error(f"--real: {exc}")


if __name__ == "__main__":
    main()
