"""Time our warp against kornia's ``warp_frame_depth`` in the same run: forward, and forward + backward.

    python benchmarks/bench_warp.py [--batch 12] [--size 256] [--threads 2] [--repeats 20] [--device cpu]

Both warps get identical inputs; runs alternate between the two so that load from other processes hits
both alike, and the median of the repeats is reported. Prints one line per measurement and the ratios
(kornia time / ours: above 1 means ours is faster).
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable

import torch
from kornia.geometry.depth import warp_frame_depth

from endoflow.geometry.pose import pose_vec_to_matrix
from endoflow.geometry.warp import warp_frame


def make_inputs(batch: int, size: int, device: torch.device) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    focal = size * 0.5
    K = torch.tensor([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]])
    return {
        "image": torch.rand(batch, 3, size, size, generator=generator).to(device),
        "depth": (1 + 4 * torch.rand(batch, 1, size, size, generator=generator)).to(device),
        "T": pose_vec_to_matrix(0.05 * torch.randn(batch, 6, generator=generator)).to(device),
        "K": K.expand(batch, 3, 3).contiguous().to(device),
    }


def ours(inputs: dict[str, torch.Tensor]) -> torch.Tensor:
    return warp_frame(inputs["image"], inputs["depth"], inputs["T"], inputs["K"])[0]


def kornia_warp(inputs: dict[str, torch.Tensor]) -> torch.Tensor:
    return warp_frame_depth(inputs["image"], inputs["depth"], inputs["T"], inputs["K"])


def step(warp: Callable, inputs: dict[str, torch.Tensor], backward: bool) -> None:
    if backward:
        inputs = {**inputs, "image": inputs["image"].requires_grad_(), "depth": inputs["depth"].requires_grad_()}
        warp(inputs).mean().backward()
    else:
        with torch.no_grad():
            warp(inputs)
    if inputs["image"].device.type == "cuda":
        torch.cuda.synchronize()


def detached(inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """New leaf tensors each run, so that ``requires_grad_`` never leaks between runs."""
    return {key: value.detach() for key, value in inputs.items()}


def median_ms(warps: dict[str, Callable], inputs: dict, backward: bool, repeats: int) -> dict[str, float]:
    times: dict[str, list[float]] = {name: [] for name in warps}
    for warp in warps.values():
        step(warp, detached(inputs), backward)  # warm-up: caches, allocator, first-call overheads
    for _ in range(repeats):
        for name, warp in warps.items():
            fresh = detached(inputs)
            start = time.perf_counter()
            step(warp, fresh, backward)
            times[name].append(1000 * (time.perf_counter() - start))
    return {name: statistics.median(values) for name, values in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=12)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    inputs = make_inputs(args.batch, args.size, device)
    difference = (ours(inputs) - kornia_warp(inputs)).abs().max().item()
    print(f"warp {args.batch}x3x{args.size}x{args.size} on {device}, {args.threads} threads, "
          f"median of {args.repeats}; max |ours - kornia| = {difference:.2e}")
    warps = {"ours": ours, "kornia": kornia_warp}
    for label, backward in (("forward", False), ("forward+backward", True)):
        ms = median_ms(warps, inputs, backward, args.repeats)
        print(f"{label:>17}: ours {ms['ours']:7.1f} ms   kornia {ms['kornia']:7.1f} ms   "
              f"ratio kornia/ours {ms['kornia'] / ms['ours']:.2f}x")


if __name__ == "__main__":
    main()
