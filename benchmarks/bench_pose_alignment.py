"""How well two frames can pin down the camera motion at a given resolution: the upper bound for a PoseNet.

    python benchmarks/bench_pose_alignment.py [--sizes 64 128 256] [--sequences S5 B5] [--frames 20]
                                              [--iterations 1000] [--lr 1e-3] [--stride 1] [--threads 2]
                                              [--losses ssim_l1:0.85 ssim_l1:0 mse]
                                              [--layout simcol|endoslam] [--model models/endoflow.pt]

For the built-in SimCol3D test sequences named (the default data: ``Params().synth`` and its seed, each path as
the synthesize stage renders it; until ``--model`` came, the test sequences' paths were scripted over 60 frames,
not their 120), each pair of frames is rendered at every size and its relative pose is found by photometric
alignment with the *ground-truth* depth: the 6-DoF pose that minimises a photometric loss through the training
warp (SSIM + L1 unless ``--losses`` says otherwise; Adam with a cosine-decayed step, converged at the defaults:
2000 steps give the same figures as 1000 for SSIM + L1, L1 and MSE), started from constant velocity (the mean
relative pose of the built-in SimCol3D I/II training sequences, as the evaluation's baseline). It is the pose the
training loss itself prefers when depth is perfect, what a PoseNet trained on that loss aims at. ``--stride k``
pairs frame t with frame t + k (constant velocity: k mean steps). Prints, per size and loss, the median rotation
error (degrees) and translation error (cm, metric: the depth is the true one) of constant velocity and of the
alignment, and how many pixels the median pair's rotation moves the image centre. It also prints the scale the
loss prefers for the translation: the median over pairs of the aligned translation projected on the true one, over
the true one's length (1: the loss is unbiased; below 1: it pulls the motion towards none). ``--losses`` aligns
once per photometric error given: ``mse`` (the paper's) or ``ssim_l1:W``, SSIM's share ``W`` of SSIM + L1 (0.85:
Monodepth2's and the default; 0: L1 alone). ``--layout endoslam`` takes the built-in EndoSLAM sequences instead
(``--sequences colon intestine``).

``--model`` asks the same of a trained model's *own* depth, which is what its pose network's loss sees: the
sequences are then those of the model's params (its synth settings and seed), the size its ``data.size``, and the
depth the model's prediction for each frame; every frame is then made as the model's data made it (rendered at
``synth.size``, written as 8-bit pixels, resized to ``data.size`` as the shards store it; the true depth is not
quantised as stored). A depth in the wrong scale moves the preferred translation with it, so the figure to read is
the path's scale over the depth's, defined as the evaluation defines it but over all the pairs at once: the
least-squares scale that takes the estimated translations to the true ones, over the depth scale, the median over
frames of ``median(true) / median(predicted)``. It is printed for the alignment with the true depth, for the
alignment with the model's depth (started, as the others, from the metric constant velocity), and for the model's
pose network on the same pairs (its mean, ``--stride 1`` only). Above 1: the path is short for its depth.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from endoflow.config import Params
from endoflow.data.frame_encoding import resize_depth, resize_rgb
from endoflow.errors import DataFormatError
from endoflow.evaluation.metrics import fit_translation_scale, paper_depth_errors
from endoflow.geometry.pose import matrix_to_pose_vec, mean_step, pose_vec_to_matrix, relative_pose, rotation_angle_deg
from endoflow.geometry.warp import warp_frame
from endoflow.losses.photometric import photometric_error
from endoflow.models.endoflow_model import EndoflowModel, load_trained_model
from endoflow.synth.render import render_tube_frame
from endoflow.synth.writers import (in_view, plan_layout, simcol_intrinsics, to_uint8, tube_sequence,
                                    unitycam_intrinsics)

DEFAULT_SEQUENCES = {"simcol": ["S5", "B5"], "endoslam": ["colon"]}


def layout_intrinsics(layout: str, size: int, look: str) -> np.ndarray:
    """The K the layout's reader derives for ``size``-px frames rendered in ``look``."""
    return simcol_intrinsics(size, look) if layout == "simcol" else unitycam_intrinsics(size)


def builtin_jobs(params: Params, layout: str = "simcol") -> dict:
    """The built-in jobs of ``layout`` (``simcol`` or ``endoslam``) by sequence name, as the synthesize stage
    renders them with ``params``."""
    return {job.name: job for job in plan_layout(layout, Path("unused"), params=params, device="cpu").jobs}


def constant_velocity(params: Params, jobs: dict, stride: int) -> np.ndarray:
    """``T_src_tgt`` (source = ``stride`` frames later) of the mean relative pose over the I/II training
    sequences."""
    held_out = set(params.data.simcol.val) | set(params.data.simcol.test)
    training = [tube_sequence(job).poses for name, job in jobs.items()
                if name not in held_out and not name.startswith("O")]
    mean_cur_next = mean_step(np.concatenate([relative_pose(p[:-1], p[1:]) for p in training]))
    return np.linalg.inv(np.linalg.matrix_power(mean_cur_next, stride))


def parse_loss(loss: str) -> tuple[str, float]:
    """``mse`` or ``ssim_l1:W`` as :func:`photometric_error`'s kind and SSIM share."""
    kind, _, weight = loss.partition(":")
    if kind == "mse" and not weight:
        return kind, 0.0
    if kind == "ssim_l1":
        try:
            return kind, float(weight)
        except ValueError:
            pass
    raise ValueError(f"a loss is 'mse' or 'ssim_l1:W' with W SSIM's share, got {loss!r}")


def align(target: torch.Tensor, source: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, start: np.ndarray,
          iterations: int, lr: float, photometric: str = "ssim_l1:0.85") -> np.ndarray:
    """Poses ``T_src_tgt [B, 4, 4]`` minimising the masked photometric error of the warp (``photometric`` as
    :func:`parse_loss` reads it), from ``start``."""
    kind, ssim_weight = parse_loss(photometric)
    vector = matrix_to_pose_vec(torch.from_numpy(start)).float().repeat(len(target), 1).requires_grad_(True)
    optimiser = torch.optim.Adam([vector], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, iterations)
    for _ in range(iterations):
        warped, valid = warp_frame(source, depth, pose_vec_to_matrix(vector), K)
        error = photometric_error(warped, target, kind, ssim_weight)
        # one pair's loss does not depend on another's pose: the sum keeps their gradients apart
        loss = ((error * valid).sum(dim=(1, 2, 3)) / valid.sum(dim=(1, 2, 3)).clamp_min(1)).sum()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
    return pose_vec_to_matrix(vector.detach().double()).numpy()


def pose_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation error (degrees) and translation error (cm) of ``[N, 4, 4]`` poses."""
    difference = np.linalg.inv(truth) @ estimate
    return rotation_angle_deg(difference[:, :3, :3]), np.linalg.norm(estimate[:, :3, 3] - truth[:, :3, 3], axis=1)


def translation_scale(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Median over pairs of the estimated translation projected on the true one, over the true one's length."""
    t_est, t_true = estimate[:, :3, 3], truth[:, :3, 3]
    return float(np.median((t_est * t_true).sum(axis=1) / (t_true * t_true).sum(axis=1)))


def rendered_frames(sequences: list, poses: list[np.ndarray], K: np.ndarray, size: int,
                    look: str) -> tuple[torch.Tensor, torch.Tensor]:
    """RGB ``[N, 3, H, W]`` (float, as rendered) and depth ``[N, 1, H, W]`` (cm) of every pose, rendered at
    ``size``."""
    frames = [render_tube_frame(s.scene, pose, K, size, size) for s, p in zip(sequences, poses) for pose in p]
    rgb = torch.from_numpy(np.stack([in_view(f[0], look) for f in frames])).permute(0, 3, 1, 2)
    return rgb, torch.from_numpy(np.stack([f[1] for f in frames]))[:, None]


def stored_frames(sequences: list, poses: list[np.ndarray], layout: str, params: Params,
                  size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The frames as a model trained on ``params`` sees them: rendered at ``synth.size``, written as 8-bit
    pixels, resized to ``size`` as the shards store them."""
    render_size = params.synth.size
    rgb, depth = rendered_frames(sequences, poses, layout_intrinsics(layout, render_size, params.synth.look),
                                 render_size, params.synth.look)
    pixels = to_uint8(rgb.permute(0, 2, 3, 1).numpy())
    rgb = np.stack([resize_rgb(image, size) for image in pixels]).astype(np.float32) / 255
    depth = np.stack([resize_depth(image, size) for image in depth[:, 0].numpy()])
    return torch.from_numpy(rgb).permute(0, 3, 1, 2), torch.from_numpy(depth)[:, None]


def model_depth(model: EndoflowModel, rgb: torch.Tensor) -> torch.Tensor:
    """The model's depth (cm) of ``[N, 3, H, W]`` frames."""
    with torch.no_grad():
        return torch.cat([model.predict_depth(batch) for batch in rgb.split(16)])


def depth_scale(predicted: torch.Tensor, truth: torch.Tensor) -> float:
    """Median over frames of the evaluation's per-frame depth ratio, ``median(true) / median(predicted)``."""
    return float(np.median([paper_depth_errors(t[0].numpy(), d[0].numpy())["ratio"] for d, t in zip(predicted, truth)]))


def path_over_depth(estimate: np.ndarray, truth: np.ndarray, depth_ratio: float) -> float:
    """The path's scale over the depth's as the evaluation defines it (here over all the pairs at once): the
    least-squares scale of the estimated translations onto the true ones over the depth scale (truth over
    prediction)."""
    return fit_translation_scale(truth[:, :3, 3], estimate[:, :3, 3]) / depth_ratio


def print_alignment(label: str, estimate: np.ndarray, truth: np.ndarray, cv_errors: tuple[float, float],
                    seconds: float | None, depth_ratio: float | None = None) -> None:
    rotation, translation = (float(np.median(e)) for e in pose_errors(estimate, truth))
    scale = translation_scale(estimate, truth)
    line = (f"  {label}: rotation error {rotation:.4f} deg ({rotation / cv_errors[0]:.2f} of constant velocity's), "
            f"translation error {translation:.4f} cm ({translation / cv_errors[1]:.2f}), translation scale "
            f"{scale:.3f}")
    if depth_ratio is not None:
        line += f", path / depth scale {path_over_depth(estimate, truth, depth_ratio):.3f}"
    print(line + (f"; {seconds:.0f} s" if seconds is not None else ""))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", help="default: 64 128 256, or the model's size")
    parser.add_argument("--layout", choices=sorted(DEFAULT_SEQUENCES), default="simcol")
    parser.add_argument("--sequences", nargs="+", help="default: S5 B5 (simcol), colon (endoslam)")
    parser.add_argument("--frames", type=int, default=20, help="frames per sequence (the paths' first ones)")
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam's step size (cosine decay to 0)")
    parser.add_argument("--stride", type=int, default=1, help="frames between the two frames of a pair")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--losses", nargs="+", default=["ssim_l1:0.85"],
                        help="photometric errors to align with: mse or ssim_l1:W (W: SSIM's share)")
    parser.add_argument("--model", type=Path, help="a model file: align with its depth as well, on its data")
    args = parser.parse_args()
    if args.stride < 1 or args.frames <= args.stride:
        parser.error(f"--stride must be at least 1 and below --frames, got {args.stride} and {args.frames}")
    for loss in args.losses:
        try:
            parse_loss(loss)
        except ValueError as error:
            parser.error(str(error))
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    model, params = None, Params()
    if args.model is not None:
        try:
            model, record = load_trained_model(args.model, torch.device("cpu"))
        except (OSError, DataFormatError) as error:
            parser.error(str(error))
        params = record.params
        args.sizes = args.sizes or [params.data.size]
        if args.sizes != [params.data.size]:
            parser.error(f"with --model, --sizes must be the model's size, {params.data.size}; got {args.sizes}")
        print(f"model {args.model} (epoch {record.epoch}), its data's sequences")
    args.sizes = args.sizes or [64, 128, 256]
    jobs = builtin_jobs(params, args.layout)
    names = args.sequences or DEFAULT_SEQUENCES[args.layout]
    unknown = [name for name in names if name not in jobs]
    if unknown:
        parser.error(f"no built-in {args.layout} sequence {', '.join(unknown)}; there are {', '.join(jobs)}")
    start = constant_velocity(params, builtin_jobs(params, "simcol"), args.stride)
    sequences = [tube_sequence(jobs[name]) for name in names]
    poses = [s.poses[: args.frames] for s in sequences]
    k = args.stride
    truth = np.concatenate([relative_pose(p[k:], p[:-k]) for p in poses])  # T_src_tgt, source = k frames later
    rotation_per_pair = float(np.median(rotation_angle_deg(truth[:, :3, :3])))
    cv_errors = tuple(float(np.median(e)) for e in pose_errors(np.repeat(start[None], len(truth), 0), truth))
    print(f"{len(truth)} pairs of {', '.join(names)}, {k} frame(s) apart; median motion per pair "
          f"{np.median(np.linalg.norm(truth[:, :3, 3], axis=1)) * 10:.3f} mm, {rotation_per_pair:.3f} deg")
    print(f"constant velocity: rotation error {cv_errors[0]:.4f} deg, translation error {cv_errors[1]:.4f} cm "
          f"(medians)")
    for size in args.sizes:
        K = layout_intrinsics(args.layout, size, params.synth.look)
        if model is None:
            rgb, depth = rendered_frames(sequences, poses, K, size, params.synth.look)
        else:
            rgb, depth = stored_frames(sequences, poses, args.layout, params, size)
        pair = np.concatenate([np.arange(len(p) - k) + sum(len(q) for q in poses[:i]) for i, p in enumerate(poses)])
        K_pairs = torch.from_numpy(K).float().expand(len(pair), 3, 3)
        print(f"{size:4d} px: one degree moves the image centre {K[0, 0] * np.pi / 180:.2f} px "
              f"(the median pair's rotation {K[0, 0] * np.deg2rad(rotation_per_pair):.3f} px)")
        depths = {"GT depth": (depth, 1.0 if model is not None else None)}
        if model is not None:
            predicted = model_depth(model, rgb)
            ratio = depth_scale(predicted, depth)
            depths["the model's depth"] = (predicted, ratio)
            print(f"  the model's depth: depth scale (true over predicted) {ratio:.3f}")
            if k == 1:
                with torch.no_grad():
                    network = model.predict_pose(rgb[pair], rgb[pair + k]).double().numpy()
                print_alignment("the model's pose network", network, truth, cv_errors, None, ratio)
        for loss in args.losses:
            for label, (used, ratio) in depths.items():
                began = time.perf_counter()
                estimate = align(rgb[pair], rgb[pair + k], used[pair], K_pairs, start, args.iterations, args.lr, loss)
                print_alignment(f"alignment with {label}, {loss}", estimate, truth, cv_errors,
                                time.perf_counter() - began, ratio)


if __name__ == "__main__":
    main()
