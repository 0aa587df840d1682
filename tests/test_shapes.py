"""check_shape: what a spec accepts, what it binds, and what its error says."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from endoflow.shapes import check_same_shape, check_shape


@pytest.mark.parametrize("make", [np.zeros, torch.zeros], ids=["numpy", "torch"])
def test_exact_sizes_and_names_bind_on_numpy_and_torch(make):
    assert check_shape("depth", make((4, 1, 6, 8)), "B,1,H,W") == {"B": 4, "H": 6, "W": 8}
    with pytest.raises(ValueError, match=r"depth: expected shape \[B, 1, H, W\], got \(4, 3, 6, 8\): dim 1 is 3, not 1"):
        check_shape("depth", make((4, 3, 6, 8)), "B,1,H,W")


def test_sizes_passed_back_bind_the_next_check():
    sizes = check_shape("image", torch.zeros(4, 3, 6, 8), "B,C,H,W")
    assert check_shape("depth", torch.zeros(4, 1, 6, 8), "B,1,H,W", **sizes) == {"B": 4, "C": 3, "H": 6, "W": 8}
    message = r"depth: expected shape \[B, 1, H, W\] with B=4, H=6, W=8, got \(2, 1, 6, 8\): dim 0 is 2, not B=4"
    with pytest.raises(ValueError, match=message):
        check_shape("depth", torch.zeros(2, 1, 6, 8), "B,1,H,W", **sizes)


def test_a_name_twice_in_one_spec_must_have_one_size():
    assert check_shape("square", np.zeros((3, 3)), "B,B") == {"B": 3}
    with pytest.raises(ValueError, match=r"x: expected shape \[B, B\], got \(2, 3\): dim 1 is 3, not B=2 as dim 0"):
        check_shape("x", np.zeros((2, 3)), "B,B")


def test_ellipsis_takes_any_leading_dims_and_no_fewer_than_the_rest():
    for shape in [(3, 3), (5, 3, 3), (2, 5, 3, 3)]:
        assert check_shape("K", np.zeros(shape), "...,3,3") == {}
    with pytest.raises(ValueError, match=r"K: expected shape \[\.\.\., 3, 3\], got \(5, 3, 4\): dim 2 is 4, not 3"):
        check_shape("K", np.zeros((5, 3, 4)), "...,3,3")
    with pytest.raises(ValueError, match=r"got \(3,\): rank 1, expected at least 2"):
        check_shape("K", np.zeros(3), "...,3,3")
    assert check_shape("mean", torch.zeros(2, 6, 5), "B,D,...") == {"B": 2, "D": 6}


def test_a_rank_other_than_the_spec_is_refused():
    with pytest.raises(ValueError, match=r"poses: expected shape \[N, 4, 4\], got \(4, 4\): rank 2, expected 3"):
        check_shape("poses", np.zeros((4, 4)), "N,4,4")
    with pytest.raises(ValueError, match="rank 4, expected 3"):
        check_shape("poses", np.zeros((1, 2, 4, 4)), "N,4,4")


def test_sizes_the_spec_does_not_name_pass_through():
    assert check_shape("K", torch.zeros(2, 3, 3), "B,3,3", B=2, H=6) == {"B": 2, "H": 6}


def test_a_malformed_spec_is_refused():
    with pytest.raises(ValueError, match=r"shape spec '\.\.\.,B,\.\.\.': at most one"):
        check_shape("x", np.zeros(2), "...,B,...")
    with pytest.raises(ValueError, match=r"shape spec 'B,-1': '-1' is neither"):
        check_shape("x", np.zeros((2, 2)), "B,-1")


def test_same_shape_names_both_arrays_and_their_shapes():
    check_same_shape("real", torch.zeros(2, 5), "fake", torch.zeros(2, 5))
    with pytest.raises(ValueError, match=r"fake: expected the shape of real \(2, 5\), got \(2, 6\)"):
        check_same_shape("real", torch.zeros(2, 5), "fake", np.zeros((2, 6)))
