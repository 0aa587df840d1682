"""How well two frames can pin down the camera motion at a given resolution: the upper bound for a PoseNet.

    python benchmarks/bench_pose_alignment.py [--sizes 64 128 256] [--sequences S5 B5] [--frames 20]
                                              [--iterations 1000] [--lr 1e-3] [--stride 1] [--threads 2]
                                              [--losses ssim_l1:0.85 ssim_l1:0 mse]

For the built-in SimCol3D test sequences named (the default data: ``Params().synth`` and its seed), each
pair of frames is rendered at every size and its relative pose is found by photometric alignment with the
*ground-truth* depth: the 6-DoF pose that minimises a photometric loss through the training warp (SSIM + L1
unless ``--losses`` says otherwise; Adam with a cosine-decayed step, converged at the defaults: 2000 steps give
the same figures as 1000 for SSIM + L1, L1 and MSE), started from
constant velocity (the mean relative pose of the built-in SimCol3D I/II training sequences, as the
evaluation's baseline). It is the pose the training loss itself prefers when depth is perfect, what a
PoseNet trained on that loss aims at. ``--stride k`` pairs frame t with frame t + k (constant velocity: k
mean steps). Prints, per size and loss, the median rotation error (degrees) and translation error (cm, metric: the
depth is the true one) of constant velocity and of the alignment, and how many pixels the median pair's
rotation moves the image centre. It also prints the scale the loss prefers for the translation: the median over
pairs of the aligned translation projected on the true one, over the true one's length (1: the loss is unbiased;
below 1: it pulls the motion towards none). ``--losses`` aligns once per photometric error given: ``mse`` (the
paper's) or ``ssim_l1:W``, SSIM's share ``W`` of SSIM + L1 (0.85: Monodepth2's and the default; 0: L1 alone).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from endoflow.config import Params
from endoflow.geometry.pose import matrix_to_pose_vec, mean_step, pose_vec_to_matrix, relative_pose, rotation_angle_deg
from endoflow.geometry.warp import warp_frame
from endoflow.losses.photometric import photometric_error
from endoflow.synth.render import render_tube_frame
from endoflow.synth.writers import plan_jobs, simcol_intrinsics, tube_sequence


def builtin_simcol_jobs(params: Params, frames: int) -> dict:
    """The built-in SimCol3D jobs by sequence name, with ``frames`` frames (the path does not depend on it
    beyond its length)."""
    synth = params.synth
    jobs = plan_jobs("simcol", Path("unused"), synth.simcol.sequences, frames, synth.size, synth.seed, "cpu", params)
    return {job.name: job for job in jobs}


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--sequences", nargs="+", default=["S5", "B5"])
    parser.add_argument("--frames", type=int, default=20, help="frames per sequence (the paths' first ones)")
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam's step size (cosine decay to 0)")
    parser.add_argument("--stride", type=int, default=1, help="frames between the two frames of a pair")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--losses", nargs="+", default=["ssim_l1:0.85"],
                        help="photometric errors to align with: mse or ssim_l1:W (W: SSIM's share)")
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
    params = Params()
    jobs = builtin_simcol_jobs(params, params.synth.simcol.frames)
    start = constant_velocity(params, jobs, args.stride)
    sequences = [tube_sequence(jobs[name]) for name in args.sequences]
    poses = [s.poses[: args.frames] for s in sequences]
    k = args.stride
    truth = np.concatenate([relative_pose(p[k:], p[:-k]) for p in poses])  # T_src_tgt, source = k frames later
    rotation_per_pair = float(np.median(rotation_angle_deg(truth[:, :3, :3])))
    cv_rotation, cv_translation = pose_errors(np.repeat(start[None], len(truth), 0), truth)
    print(f"{len(truth)} pairs of {', '.join(args.sequences)}, {k} frame(s) apart; median motion per pair "
          f"{np.median(np.linalg.norm(truth[:, :3, 3], axis=1)) * 10:.3f} mm, {rotation_per_pair:.3f} deg")
    print(f"constant velocity: rotation error {np.median(cv_rotation):.4f} deg, translation error "
          f"{np.median(cv_translation):.4f} cm (medians)")
    for size in args.sizes:
        K = simcol_intrinsics(size)
        frames = [[render_tube_frame(s.scene, pose, K, size, size) for pose in p] for s, p in zip(sequences, poses)]
        rgb = torch.from_numpy(np.stack([f[0] for seq in frames for f in seq])).permute(0, 3, 1, 2)
        depth = torch.from_numpy(np.stack([f[1] for seq in frames for f in seq]))[:, None]
        pair = np.concatenate([np.arange(len(p) - k) + sum(len(q) for q in poses[:i]) for i, p in enumerate(poses)])
        for loss in args.losses:
            began = time.perf_counter()
            estimate = align(rgb[pair], rgb[pair + k], depth[pair], torch.from_numpy(K).float().expand(len(pair), 3, 3),
                             start, args.iterations, args.lr, loss)
            rotation, translation = (float(np.median(e)) for e in pose_errors(estimate, truth))
            print(f"{size:4d} px: one degree moves the image centre {K[0, 0] * np.pi / 180:.2f} px "
                  f"(the median pair's rotation {K[0, 0] * np.deg2rad(rotation_per_pair):.3f} px); alignment with "
                  f"GT depth, {loss}: rotation error {rotation:.4f} deg "
                  f"({rotation / np.median(cv_rotation):.2f} of constant velocity's), translation error "
                  f"{translation:.4f} cm ({translation / np.median(cv_translation):.2f}), translation scale "
                  f"{translation_scale(estimate, truth):.3f}; {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
