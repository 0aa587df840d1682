"""Shape checks: an array's shape against a spec such as ``"B,1,H,W"``, with one wording for every module.

A spec is comma-separated dims: a number is that exact size, a name (``B``, ``H``, ``W``, ...) binds to the
size it first meets, and one ``...`` stands for any number of dims. Sizes bound by one check are passed to the
next as keywords, so arguments that must agree are checked against each other::

    sizes = check_shape("image_src", image_src, "B,C,H,W")
    check_shape("depth_tgt", depth_tgt, "B,1,H,W", **sizes)

Works on anything with a ``.shape`` (torch tensors, numpy arrays). These checks run in training's hot path,
so a spec is parsed once (cached) and a passing check only compares integers.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

ELLIPSIS = "..."


@lru_cache(maxsize=None)
def _parse(spec: str) -> tuple[int, bool, tuple[tuple[int, int | str], ...]]:
    """``(rank, open, checks)``: the number of named or numbered dims, whether ``...`` allows more, and
    ``(position, size or name)`` per dim; positions after ``...`` count from the end (negative)."""
    tokens = [token.strip() for token in spec.split(",")] if spec.strip() else []
    if tokens.count(ELLIPSIS) > 1:
        raise ValueError(f"shape spec {spec!r}: at most one '...'")
    split = tokens.index(ELLIPSIS) if ELLIPSIS in tokens else len(tokens)
    head, tail = tokens[:split], tokens[split + 1 :]
    positions = [*range(len(head)), *range(-len(tail), 0)]
    checks = tuple((position, _dim(token, spec)) for position, token in zip(positions, head + tail))
    return len(checks), ELLIPSIS in tokens, checks


def _dim(token: str, spec: str) -> int | str:
    if token.isdigit():
        return int(token)
    if token.isidentifier():
        return token
    raise ValueError(f"shape spec {spec!r}: {token!r} is neither a size, a name nor '...'")


def check_shape(name: str, array: Any, spec: str, **sizes: int) -> dict[str, int]:
    """Check ``array.shape`` against ``spec``; returns ``sizes`` with every name of ``spec`` bound.

    Args:
        name: the argument's name, as the error should call it.
        array: a torch tensor or numpy array.
        spec: e.g. ``"B,1,H,W"``, ``"...,3,3"``, ``"N,4,4"``, ``"B,D,..."``.
        sizes: sizes some names must have (e.g. ``B=4``); names the spec does not use are passed through.

    Raises:
        ValueError: naming the argument, the expected shape with the sizes given, the actual shape and the
            first dim that differs, e.g. ``depth: expected shape [B, 1, H, W] with B=4, got (4, 3, 64, 64):
            dim 1 is 3, not 1``.
    """
    shape = array.shape
    rank, open_, checks = _parse(spec)
    if (len(shape) < rank) if open_ else (len(shape) != rank):
        raise ValueError(_mismatch(name, shape, spec, sizes))
    bound = sizes.copy()
    for position, want in checks:
        got = shape[position]
        if want.__class__ is int:
            if got != want:
                raise ValueError(_mismatch(name, shape, spec, sizes))
        elif bound.setdefault(want, got) != got:
            raise ValueError(_mismatch(name, shape, spec, sizes))
    return bound


def check_same_shape(first_name: str, first: Any, second_name: str, second: Any) -> None:
    """Check that ``second`` has exactly ``first``'s shape, whatever its rank (e.g. a loss's two inputs)."""
    if tuple(first.shape) != tuple(second.shape):
        raise ValueError(f"{second_name}: expected the shape of {first_name} {tuple(first.shape)}, "
                         f"got {tuple(second.shape)}")


def _mismatch(name: str, shape: Any, spec: str, given: dict[str, int]) -> str:
    """The error of a failed :func:`check_shape` (cold path: it walks the spec again to say why)."""
    rank, open_, checks = _parse(spec)
    shape = tuple(shape)
    expected = ", ".join(token.strip() for token in spec.split(",")) if spec.strip() else ""
    names_given = [f"{want}={given[want]}" for _, want in checks if isinstance(want, str) and want in given]
    with_sizes = f" with {', '.join(dict.fromkeys(names_given))}" if names_given else ""
    return f"{name}: expected shape [{expected}]{with_sizes}, got {shape}: {_reason(shape, rank, open_, checks, given)}"


def _reason(shape: tuple[int, ...], rank: int, open_: bool, checks: tuple, given: dict[str, int]) -> str:
    if (len(shape) < rank) if open_ else (len(shape) != rank):
        return f"rank {len(shape)}, expected {'at least ' if open_ else ''}{rank}"
    first_dim: dict[str, int] = {}
    for position, want in checks:
        dim = position % len(shape)
        got = shape[dim]
        if isinstance(want, int):
            if got != want:
                return f"dim {dim} is {got}, not {want}"
        elif want in given:
            if got != given[want]:
                return f"dim {dim} is {got}, not {want}={given[want]}"
        elif want in first_dim:
            if got != shape[first_dim[want]]:
                return f"dim {dim} is {got}, not {want}={shape[first_dim[want]]} as dim {first_dim[want]}"
        else:
            first_dim[want] = dim
    raise AssertionError(f"shape {shape} matches the spec it failed")  # unreachable: check_shape found a mismatch
