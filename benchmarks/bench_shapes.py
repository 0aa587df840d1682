"""Does checking shapes through ``check_shape`` slow the training step? Time per call of the checks
``warp_frame`` runs (four arrays, sizes bound across them) and of one ``...,3,3`` check, through
``check_shape`` and as the inline comparisons they replaced, interleaved, best of ``--repeats``; and, for scale,
one ``warp_frame`` at the training size.

    python benchmarks/bench_shapes.py [--calls 10000] [--repeats 5]

Figures are printed, not asserted: they depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import time
from typing import Callable

import torch

from endoflow.geometry.warp import warp_frame
from endoflow.shapes import check_shape

BATCH, HEIGHT, WIDTH = 8, 64, 64


def inline_warp_checks(image: torch.Tensor, depth: torch.Tensor, T: torch.Tensor, K: torch.Tensor) -> None:
    """The hand-written checks ``warp.py`` had before ``check_shape``."""
    if image.ndim != 4:
        raise ValueError("image_src")
    batch, _, height, width = image.shape
    for name, tensor, shape in (("depth_tgt", depth, (batch, 1, height, width)), ("T_src_tgt", T, (batch, 4, 4)),
                                ("K", K, (batch, 3, 3))):
        if tuple(tensor.shape) != shape:
            raise ValueError(name)


def helper_warp_checks(image: torch.Tensor, depth: torch.Tensor, T: torch.Tensor, K: torch.Tensor) -> None:
    sizes = check_shape("image_src", image, "B,C,H,W")
    check_shape("depth_tgt", depth, "B,1,H,W", **sizes)
    check_shape("T_src_tgt", T, "B,4,4", **sizes)
    check_shape("K", K, "B,3,3", **sizes)


def inline_last_dims(K: torch.Tensor) -> None:
    if K.shape[-2:] != (3, 3):
        raise ValueError("K")


def helper_last_dims(K: torch.Tensor) -> None:
    check_shape("K", K, "...,3,3")


def seconds_per_call(check: Callable[[], None], calls: int) -> float:
    start = time.perf_counter()
    for _ in range(calls):
        check()
    return (time.perf_counter() - start) / calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    image, depth = torch.rand(BATCH, 3, HEIGHT, WIDTH), torch.full((BATCH, 1, HEIGHT, WIDTH), 5.0)
    T, K = torch.eye(4).expand(BATCH, 4, 4).clone(), torch.eye(3).expand(BATCH, 3, 3).clone()
    cases = {
        "warp_frame's 4 checks": (lambda: inline_warp_checks(image, depth, T, K),
                                  lambda: helper_warp_checks(image, depth, T, K)),
        "one [..., 3, 3] check": (lambda: inline_last_dims(K), lambda: helper_last_dims(K)),
    }
    best = {name: [float("inf"), float("inf")] for name in cases}
    for _ in range(args.repeats):
        for name, checks in cases.items():
            for i, check in enumerate(checks):
                best[name][i] = min(best[name][i], seconds_per_call(check, args.calls))
    warp = min(seconds_per_call(lambda: warp_frame(image, depth, T, K), 20) for _ in range(args.repeats))
    print(f"{args.calls} calls, best of {args.repeats}; one thread")
    print(f"{'case':<24}{'inline us':>11}{'check_shape us':>16}{'ratio':>8}")
    for name, (inline, helper) in best.items():
        print(f"{name:<24}{inline * 1e6:>11.2f}{helper * 1e6:>16.2f}{helper / inline:>8.2f}")
    added = best["warp_frame's 4 checks"][1] - best["warp_frame's 4 checks"][0]
    print(f"warp_frame at {BATCH} x {HEIGHT} x {WIDTH}: {warp * 1e6:.0f} us; the helper adds {added * 1e6:.2f} us "
          f"({100 * added / warp:.3f} %)")


if __name__ == "__main__":
    main()
