"""Why a trained pose network answers nearly one step for every pair: what it predicts against the truth, and what
its training loss can tell it.

    python benchmarks/bench_pose_collapse.py --model models/endoflow.pt --shards data/shards/simcol
                                             [--split val] [--samples 240] [--threads 2]

Over the split's (cur, next) pairs, with the shards' exact depth and poses, prints:

- the spread of the predicted step length against the true one (standard deviations, correlation), and per pose
  component the spread of the prediction, of the truth and of the VAE's sampling noise (``exp(logvar / 2)``);
- how far the true motion moves the image (median and 90th percentile pixel displacement, exact depth);
- what auto-masking leaves: the share of pixels whose unwarped neighbour already matches better than the exact
  warp (exact depth and pose), which then give no gradient;
- the training loss (the default objective's photometric term for the pair, the model's depth) at the true pose,
  at the network's, at the training set's mean step (constant velocity) and at the true pose with its translation
  scaled by 0.5 ... 1.5: how much lower the truth is than one step for all, the signal that would make the
  network follow the motion;
- the same loss at the true pose and at the network's run backwards (their inverses): whether the loss, with the
  model's depth, tells the direction of the motion, and whether a network that answers against it sits on the
  wrong side of what its loss prefers (time reversal, ``train.time_reversal``, asks a network for both directions);
- the gradient the pose receives: the loss's gradient with respect to the network's answer (the pose vector), and
  on how many pairs a step against it moves the answer towards the truth (translation and rotation apart);
- by phase of the true motion (advancing, paused, withdrawing: the forward component beyond ``PHASE_CM`` either
  way, or within it): the network's forward component against the truth's, the share of pixels the warp at the
  network's answer (the model's depth) explains better than the unwarped neighbour, the only pixels auto-masking
  lets reach the pose, and the gradient the translation receives there; then the same without auto-masking;
- the output scaling: the answer is ``MEAN_SCALE * (bias + W . features)`` (the head's 1x1 convolution, averaged
  over the image); per component, the bias's part of the mean answer and the spread the features give it, against
  the truth's mean and spread;
- with ``--probe-samples N``: whether the motion is in the features at all. Ridge regressions from the head's
  input, averaged over the image as the head sees it or kept per position (the mean could cancel a radial flow,
  which is what moving forward makes), are fitted to the true motion of N training pairs (the weight of the
  ridge chosen by 5-fold cross-validation on them) and scored on the split's pairs: their correlation with the
  truth beside the network's.
"""

from __future__ import annotations

import argparse
import time
from typing import Callable, Sequence

import numpy as np
import torch

from endoflow.config import LossConfig
from endoflow.data.loader import list_shards, triplet_dataset
from endoflow.devices import use_cpu_threads
from endoflow.geometry.pose import invert_pose, matrix_to_pose_vec, mean_step, pose_vec_to_matrix
from endoflow.geometry.warp import project_target_pixels, warp_frame
from endoflow.losses.photometric import identity_error, reprojection_loss
from endoflow.models.endoflow_model import load_trained_model
from endoflow.models.pose_net import MEAN_SCALE

SCALES = (0.5, 0.75, 1.0, 1.25, 1.5)
PHASE_CM = 0.05  # half the colon styles' slowest speed: a step shorter than this along the axis is a pause
RIDGE_WEIGHTS = tuple(10.0 ** k for k in range(-2, 7))


def pairs(shards: str, split: str, count: int) -> list[dict]:
    """Up to ``count`` samples of ``split`` with poses and depth, spread over the split (every k-th)."""
    samples = [s for s in triplet_dataset(list_shards(shards, split))
               if s["meta"]["T_world_cam"]["cur"] is not None and s["meta"]["T_world_cam"]["next"] is not None]
    step = max(1, len(samples) // count)
    return samples[::step][:count]


def loss_at(cur: torch.Tensor, nxt: torch.Tensor, depth: torch.Tensor, T_next_cur: torch.Tensor, K: torch.Tensor,
            cfg: LossConfig) -> torch.Tensor:
    """Per-pair photometric loss ``[B]`` of ``cur`` rebuilt from ``nxt`` (auto-masked as in training)."""
    warped = warp_frame(nxt, depth, T_next_cur, K)[0]
    _, per_pixel, _ = reprojection_loss([warped], cur, [nxt], cfg, identity_error(cur, [nxt], cfg))
    return per_pixel.mean(dim=(1, 2, 3))


def print_pose_gradient(cur: torch.Tensor, nxt: torch.Tensor, depth: torch.Tensor, answer: torch.Tensor,
                        truth: torch.Tensor, K: torch.Tensor, cfg: LossConfig) -> None:
    """Where the loss pushes the network's answer ``[B, 6]``: the share of pairs whose negative gradient points
    towards ``truth`` (positive cosine with ``truth - answer``), for the rotation and the translation apart."""
    pose = answer.clone().requires_grad_(True)
    loss_at(cur, nxt, depth, pose_vec_to_matrix(pose), K, cfg).sum().backward()
    descent, towards = -pose.grad, truth - answer
    for part, columns in (("rotation", slice(0, 3)), ("translation", slice(3, 6))):
        cosine = torch.nn.functional.cosine_similarity(descent[:, columns], towards[:, columns], dim=1)
        print(f"  gradient at the network's answer, {part}: a step against it moves towards the truth on "
              f"{(cosine > 0).float().mean():.1%} of pairs (median cosine {cosine.median():+.2f}); median |gradient| "
              f"{descent[:, columns].norm(dim=1).median():.3e} per {'rad' if part == 'rotation' else 'cm'}")


def print_by_phase(cur: torch.Tensor, nxt: torch.Tensor, depth: torch.Tensor, answer: torch.Tensor,
                   truth: torch.Tensor, K: torch.Tensor, cfg: LossConfig) -> None:
    """Per phase of the true motion (``T_next_cur``'s forward component: negative while advancing): the network's
    forward component, the pixels auto-masking leaves to the warp at its answer, the translation's gradient."""
    pose = answer.clone().requires_grad_(True)
    warped = warp_frame(nxt, depth, pose_vec_to_matrix(pose), K)[0]
    _, per_pixel, kept = reprojection_loss([warped], cur, [nxt], cfg, identity_error(cur, [nxt], cfg))
    per_pixel.mean(dim=(1, 2, 3)).sum().backward()
    descent, towards = -pose.grad[:, 3:], (truth - answer)[:, 3:]
    cosine = torch.nn.functional.cosine_similarity(descent, towards, dim=1)
    left = kept.float().mean(dim=(1, 2, 3))
    forward = truth[:, 5]
    phases = {"advancing": forward < -PHASE_CM, "paused": forward.abs() <= PHASE_CM, "withdrawing": forward > PHASE_CM}
    print(f"by phase of the true motion (forward component beyond {PHASE_CM} cm, or within it), auto-masking "
          f"{'on' if cfg.automask else 'off'}: pairs; tz truth / network (mean, cm); pixels left to the warp at the "
          f"network's answer; translation gradient: median |.|, share towards the truth")
    for name, chosen in phases.items():
        if not chosen.any():
            print(f"  {name}: no pairs")
            continue
        print(f"  {name}: {int(chosen.sum())}; {forward[chosen].mean():+.4f} / {answer[chosen, 5].mean():+.4f}; "
              f"{left[chosen].mean():.1%}; {descent[chosen].norm(dim=1).median():.3e} per cm, "
              f"{(cosine[chosen] > 0).float().mean():.1%}")


def print_output_scaling(model: torch.nn.Module, cur: torch.Tensor, nxt: torch.Tensor, truth: np.ndarray) -> None:
    """The answer's two parts: ``MEAN_SCALE * bias`` (the same for every pair) and ``MEAN_SCALE * W . features``."""
    head = model.pose_net.mean_head
    features = head_input(model, cur, nxt).mean(dim=(2, 3))
    with torch.no_grad():
        varying = (MEAN_SCALE * features @ head.weight[:, :, 0, 0].T).double().numpy()
    constant = MEAN_SCALE * head.bias.detach().double().numpy()
    print("output scaling (MEAN_SCALE * raw): per component, the bias's part / the features' mean part (their "
          "spread) / the truth's mean (spread)")
    for i, name in enumerate(("rx", "ry", "rz", "tx", "ty", "tz")):
        print(f"  {name}: {constant[i]:+.2e} / {varying[:, i].mean():+.2e} ({varying[:, i].std():.2e}) / "
              f"{truth[:, i].mean():+.2e} ({truth[:, i].std():.2e})")


def head_input(model: torch.nn.Module, cur: torch.Tensor, nxt: torch.Tensor) -> torch.Tensor:
    """``[B, C, h, w]``: what the pose network's head reads (the trunk's output), per position."""
    captured: list[torch.Tensor] = []
    hook = model.pose_net.mean_head.register_forward_hook(lambda module, inputs, output: captured.append(inputs[0]))
    with torch.no_grad():
        model.forward_motion(cur, nxt, sample=False)
    hook.remove()
    return captured[0]


Predictor = Callable[[np.ndarray], np.ndarray]


def fitted_ridge(X: np.ndarray, y: np.ndarray, weights: Sequence[float] = RIDGE_WEIGHTS,
                 folds: int = 5) -> tuple[Predictor, float]:
    """A ridge regression on standardised ``X`` and the weight chosen for it by ``folds``-fold cross-validation
    (squared error) over contiguous folds (the pairs come in sequence order, and neighbouring frames are near
    copies of each other)."""
    parts = np.arange(len(y)) * folds // len(y)

    def error(weight: float) -> float:
        return sum(float(np.square(ridge(X[parts != k], y[parts != k], weight)(X[parts == k]) - y[parts == k]).sum())
                   for k in range(folds))
    chosen = min(weights, key=error)
    return ridge(X, y, chosen), chosen


def ridge(X: np.ndarray, y: np.ndarray, weight: float) -> Predictor:
    """Ridge regression of ``y`` on standardised ``X``, solved in the smaller of its two equivalent forms (more
    features than samples: the samples' Gram matrix)."""
    mean, scale = X.mean(0), X.std(0) + 1e-6
    Z, centred = (X - mean) / scale, y - y.mean()
    if Z.shape[1] <= Z.shape[0]:
        w = np.linalg.solve(Z.T @ Z + weight * np.eye(Z.shape[1]), Z.T @ centred)
    else:
        w = Z.T @ np.linalg.solve(Z @ Z.T + weight * np.eye(Z.shape[0]), centred)
    return lambda Xb: ((Xb - mean) / scale) @ w + y.mean()


def print_linear_probes(model: torch.nn.Module, training: list[dict], cur: torch.Tensor, nxt: torch.Tensor,
                        truth: np.ndarray, predicted: np.ndarray) -> None:
    """Per pose component: the network's correlation with the truth, and that of ridge probes fitted on the
    ``training`` pairs from the head's input averaged over the image and kept per position."""
    train_cur, train_nxt, T_train = pair_tensors(training)
    train_truth = matrix_to_pose_vec(T_train.double()).numpy()
    maps = [head_input(model, c, n).double() for c, n in ((train_cur, train_nxt), (cur, nxt))]  # training, scored
    matrices = {"averaged": [m.mean(dim=(2, 3)).numpy() for m in maps],
                "per position": [m.flatten(1).numpy() for m in maps]}
    print(f"linear probes fitted on {len(training)} training pairs: correlation with the truth, the network / the "
          f"head's input averaged / per position (the ridge weights chosen)")
    for i, name in enumerate(("rx", "ry", "rz", "tx", "ty", "tz")):
        probes = [fitted_ridge(fitted_on, train_truth[:, i]) for fitted_on, _ in matrices.values()]
        scores = [np.corrcoef(predict(scored), truth[:, i])[0, 1]
                  for (predict, _), (_, scored) in zip(probes, matrices.values())]
        print(f"  {name}: {np.corrcoef(predicted[:, i], truth[:, i])[0, 1]:+.2f} / {scores[0]:+.2f} / "
              f"{scores[1]:+.2f} ({probes[0][1]:g}, {probes[1][1]:g})")


def pair_tensors(samples: list[dict]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``cur``, ``next`` ``[B, 3, H, W]`` in [0, 1] and the forward motion the network predicts, ``T_next_cur
    [B, 4, 4]``, of ``samples``."""
    cur = torch.stack([s["cur"] for s in samples]).float()
    nxt = torch.stack([s["next"] for s in samples]).float()
    if cur.max() > 1:
        cur, nxt = cur / 255, nxt / 255
    world = {name: torch.tensor(np.stack([s["meta"]["T_world_cam"][name] for s in samples]), dtype=torch.float32)
             for name in ("cur", "next")}
    return cur, nxt, invert_pose(world["next"]) @ world["cur"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="models/endoflow.pt")
    parser.add_argument("--shards", default="data/shards/simcol")
    parser.add_argument("--split", default="val")
    parser.add_argument("--samples", type=int, default=240)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--probe-samples", type=int, default=0,
                        help="fit linear probes on this many training pairs (0: none)")
    args = parser.parse_args()
    use_cpu_threads(args.threads)
    torch.manual_seed(0)
    began = time.perf_counter()
    model, record = load_trained_model(args.model, torch.device("cpu"))
    model.eval()
    samples = pairs(args.shards, args.split, args.samples)
    cur, nxt, T_next_cur = pair_tensors(samples)
    K = torch.stack([torch.as_tensor(s["meta"]["K"], dtype=torch.float32) for s in samples])
    gt_depth = torch.stack([s["depth"] for s in samples]).float()
    truth = matrix_to_pose_vec(T_next_cur.double()).numpy()
    with torch.no_grad():
        _, mean, logvar = model.forward_motion(cur, nxt, sample=False)
        depth = model.predict_depth(cur)
    predicted = mean.double().numpy()
    true_step, pred_step = np.linalg.norm(truth[:, 3:], axis=1), np.linalg.norm(predicted[:, 3:], axis=1)
    print(f"{len(samples)} {args.split} pairs of {args.shards}; model {args.model} (trained {record.epoch} epochs)")
    print(f"step length: true {true_step.mean() * 10:.3f} ± {true_step.std() * 10:.3f} mm, predicted "
          f"{pred_step.mean() * 10:.3f} ± {pred_step.std() * 10:.3f} mm (model scale); spread ratio "
          f"{pred_step.std() / pred_step.mean() / (true_step.std() / true_step.mean()):.2f} (coefficients of "
          f"variation); correlation {np.corrcoef(true_step, pred_step)[0, 1]:.3f}")
    noise = np.exp(0.5 * logvar.double().numpy()) if logvar is not None else np.zeros_like(predicted)
    names = ("rx", "ry", "rz", "tx", "ty", "tz")
    print("per component (rad, cm): std of truth / std of prediction / median VAE noise / correlation")
    for i, name in enumerate(names):
        correlation = np.corrcoef(truth[:, i], predicted[:, i])[0, 1] if predicted[:, i].std() > 0 else 0.0
        print(f"  {name}: {truth[:, i].std():.2e} / {predicted[:, i].std():.2e} / {np.median(noise[:, i]):.2e} / "
              f"{correlation:+.3f}")
    pixels, z = project_target_pixels(gt_depth, T_next_cur, K)
    height, width = cur.shape[-2:]
    grid = torch.stack(torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")[::-1]).reshape(2, -1)
    moved = (pixels - grid[None]).norm(dim=1)[gt_depth.reshape(len(samples), -1) > 0].numpy()
    print(f"image motion of the true step (exact depth): median {np.median(moved):.2f} px, 90th percentile "
          f"{np.percentile(moved, 90):.2f} px at {width} px")
    cfg = LossConfig(**{**dict(record.params.loss), "min_reprojection": False})
    warped = warp_frame(nxt, gt_depth, T_next_cur, K)[0]
    _, _, kept = reprojection_loss([warped], cur, [nxt], cfg, identity_error(cur, [nxt], cfg))
    print(f"auto-masking at the exact pose and depth leaves {kept.float().mean():.1%} of pixels to the warp "
          f"(the rest match better unwarped and give no gradient)")
    constant = torch.from_numpy(np.linalg.inv(record.baselines.mean_relative_pose)).float().expand_as(T_next_cur)
    with torch.no_grad():
        at = {"truth": loss_at(cur, nxt, depth, T_next_cur, K, cfg),
              "network": loss_at(cur, nxt, depth, pose_vec_to_matrix(mean.float()), K, cfg),
              "constant velocity": loss_at(cur, nxt, depth, constant, K, cfg),
              "truth reversed": loss_at(cur, nxt, depth, invert_pose(T_next_cur), K, cfg),
              "network reversed": loss_at(cur, nxt, depth, invert_pose(pose_vec_to_matrix(mean.float())), K, cfg)}
        scaled = {}
        for scale in SCALES:
            T = T_next_cur.clone()
            T[:, :3, 3] *= scale
            scaled[scale] = loss_at(cur, nxt, depth, T, K, cfg).mean().item()
    base = at["truth"].mean().item()
    print("photometric loss with the model's depth (mean over pairs): " + ", ".join(
        f"{name} {values.mean().item():.5f} ({values.mean().item() / base - 1:+.2%})" for name, values in at.items()))
    print(f"  pairs where the truth beats constant velocity: {(at['truth'] < at['constant velocity']).float().mean():.1%}"
          f"; the network beats it: {(at['network'] < at['constant velocity']).float().mean():.1%}")
    print(f"  pairs where the truth beats it reversed: {(at['truth'] < at['truth reversed']).float().mean():.1%}; "
          f"the network beats its answer reversed: {(at['network'] < at['network reversed']).float().mean():.1%}")
    print("  true pose with its translation scaled: " + ", ".join(
        f"x{scale:g} {value / base - 1:+.2%}" for scale, value in scaled.items()))
    print_pose_gradient(cur, nxt, depth, mean.float(), torch.from_numpy(truth).float(), K, cfg)
    for automask in (True, False):  # what the mask takes from the pose: the same pairs with it and without
        print_by_phase(cur, nxt, depth, mean.float(), torch.from_numpy(truth).float(), K,
                       LossConfig(**{**dict(cfg), "automask": automask}))
    print_output_scaling(model, cur, nxt, truth)
    if args.probe_samples:
        print_linear_probes(model, pairs(args.shards, "train", args.probe_samples), cur, nxt, truth, predicted)
    steps = mean_step(T_next_cur.double().numpy())
    print(f"the split's mean step {np.linalg.norm(steps[:3, 3]) * 10:.3f} mm; {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
