"""The training objective on real SimCol3D frames: ground truth explains the motion, and the model learns it.

Data: the ten real SimCol3D frames of ``/work/shared/samples/simcol3d`` (through our reader, so poses are
converted and K is the literal cam.txt), resized to 64x64; each target frame has its two neighbours.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np
import pytest
import torch

from endoflow.config import LossConfig, Params
from endoflow.geometry.camera import scale_intrinsics
from endoflow.geometry.pose import pose_vec_to_matrix, relative_pose
from endoflow.models.endoflow_model import build_model
from endoflow.losses.consistency import geometry_consistency
from endoflow.losses.photometric import held_out_photometric_error
from endoflow.losses.smoothness import edge_aware_smoothness
from endoflow.training.objective import reprojection, training_step_losses
from tests.samples import SIMCOL_SAMPLE

SIZE = 64
STEPS = 30
TRIPLETS = 4

pytestmark = pytest.mark.skipif(not SIMCOL_SAMPLE.is_dir(), reason="real SimCol3D sample folder not present")


def simcol_triplets(size: int = SIZE) -> dict[str, torch.Tensor]:
    """All 8 (prev, cur, next) triplets of the sample as a batch in the loader's keys, plus GT depth/poses."""
    from endoflow.data.simcol import SimColReader

    sequence = SimColReader(SIMCOL_SAMPLE, Params().data.simcol).sequences()[0]
    frames = [sequence.frame(i) for i in range(len(sequence))]
    rgb = torch.stack(
        [torch.from_numpy(cv2.resize(f.rgb, (size, size), interpolation=cv2.INTER_AREA)).permute(2, 0, 1) for f in frames]
    ).float() / 255
    depth = torch.stack(
        [torch.from_numpy(cv2.resize(f.depth_cm, (size, size), interpolation=cv2.INTER_NEAREST)) for f in frames]
    )[:, None]
    height, width = sequence.image_size
    K = torch.from_numpy(scale_intrinsics(sequence.K, size / width, size / height)).float()
    poses = [f.T_world_cam for f in frames]
    cur = range(1, len(frames) - 1)
    return {
        "prev": rgb[[c - 1 for c in cur]],
        "cur": rgb[list(cur)],
        "next": rgb[[c + 1 for c in cur]],
        "K": K.expand(len(cur), 3, 3).clone(),
        "depth": depth[list(cur)],
        "T_prev_cur": torch.from_numpy(np.stack([relative_pose(poses[c - 1], poses[c]) for c in cur])).float(),
        "T_next_cur": torch.from_numpy(np.stack([relative_pose(poses[c + 1], poses[c]) for c in cur])).float(),
    }


def loss_with(batch: dict, depth: torch.Tensor, T_prev: torch.Tensor, T_next: torch.Tensor, cfg: LossConfig) -> float:
    sources = [batch["prev"], batch["next"]]
    return reprojection(batch["cur"], sources, depth, [T_prev, T_next], batch["K"], cfg).item()


# Per-pixel MSE gains less from the right motion on these smooth, camera-lit frames than SSIM + L1 does.
@pytest.mark.parametrize("photometric, no_motion_ratio", [("ssim_l1", 0.3), ("mse", 0.9)])
def test_ground_truth_depth_and_pose_explain_the_motion_best(photometric, no_motion_ratio):
    batch = simcol_triplets()
    cfg = LossConfig(photometric=photometric, automask=False)
    gt = loss_with(batch, batch["depth"], batch["T_prev_cur"], batch["T_next_cur"], cfg)
    # A few mm and a couple of degrees off: about the size of one frame's motion.
    nudge = pose_vec_to_matrix(torch.tensor([0.03, -0.03, 0.02, 0.2, -0.2, 0.2])).expand(8, 4, 4)
    perturbed = loss_with(batch, batch["depth"], nudge @ batch["T_prev_cur"], nudge @ batch["T_next_cur"], cfg)
    identity = torch.eye(4).expand(8, 4, 4)
    no_motion = loss_with(batch, batch["depth"], identity, identity, cfg)
    assert gt < 0.5 * perturbed
    assert gt < no_motion_ratio * no_motion


def test_ground_truth_depth_beats_a_constant_depth():
    batch = simcol_triplets()
    # SSIM sees the misplaced structure; the per-pixel MSE of these smooth frames barely does.
    cfg = LossConfig(photometric="ssim_l1", automask=False)
    gt = loss_with(batch, batch["depth"], batch["T_prev_cur"], batch["T_next_cur"], cfg)
    flat = torch.full_like(batch["depth"], batch["depth"].mean().item())
    assert gt < 0.6 * loss_with(batch, flat, batch["T_prev_cur"], batch["T_next_cur"], cfg)


def test_swapping_the_pose_direction_breaks_the_reconstruction():
    batch = simcol_triplets()
    cfg = LossConfig(automask=False)
    right = loss_with(batch, batch["depth"], batch["T_prev_cur"], batch["T_next_cur"], cfg)
    inverted = loss_with(batch, batch["depth"], batch["T_prev_cur"].inverse(), batch["T_next_cur"].inverse(), cfg)
    assert right < 0.5 * inverted


def test_losses_have_every_term_and_the_total_adds_up():
    batch = simcol_triplets(size=32)
    params = Params()
    model = build_model(params, None).train()
    out = training_step_losses(model, batch, params.loss)
    for key in ("total", "photometric", "smoothness", "kl", "photometric/0", "photometric/3", "smoothness/3"):
        assert out[key].ndim == 0 and torch.isfinite(out[key])
    cfg = params.loss
    expected = out["photometric"] + cfg.smoothness_weight * out["smoothness"] + cfg.kl_weight * out["kl"]
    torch.testing.assert_close(out["total"], expected)
    assert "geometry" not in out  # weighted 0: not computed
    single = training_step_losses(model.eval(), batch, cfg.replace(multiscale=False))
    assert "photometric/1" not in single


def test_the_geometry_consistency_term_adds_its_weighted_share_and_reaches_both_networks():
    batch = simcol_triplets(size=32)
    params = Params()
    model = build_model(params, None).eval()  # deterministic: the same losses twice
    cfg = params.loss.replace(geometry_weight=0.5)
    off = training_step_losses(model, batch, params.loss)
    on = training_step_losses(model, batch, cfg)
    assert 0 < on["geometry"] < 1
    torch.testing.assert_close(on["total"], off["total"] + 0.5 * on["geometry"])
    on["geometry"].backward()
    assert model.pose_net.mean_head.weight.grad.abs().sum() > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.depth_net.parameters())


def short_optimisation(batch: dict, cfg: LossConfig, score: Callable[..., float]) -> tuple[float, float, float]:
    """:data:`STEPS` Adam steps of the model on ``batch`` (seed 0, 2 threads): ``score(depth, T_prev, T_next)`` of
    its predictions at the start, of its start depth with no motion, and at the end."""
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        model = build_model(Params(), None)
        optimiser = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=3e-4)
        identity = torch.eye(4).expand(TRIPLETS, 4, 4)

        def scores() -> tuple[float, float]:
            model.eval()
            with torch.no_grad():
                depth = model.predict_depth(batch["cur"])
                T_prev = model.predict_pose(batch["cur"], batch["prev"], source_is_next=False)
                T_next = model.predict_pose(batch["cur"], batch["next"])
                return score(depth, T_prev, T_next), score(depth, identity, identity)

        start, no_motion = scores()
        model.train()
        for _ in range(STEPS):
            optimiser.zero_grad(set_to_none=True)
            training_step_losses(model, batch, cfg)["total"].backward()
            optimiser.step()
        end, _ = scores()
    finally:
        torch.set_num_threads(threads)
    print(f"start {start:.4f} no-motion {no_motion:.4f} end {end:.4f}")
    return start, no_motion, end


def test_short_optimisation_learns_depth_and_motion():
    """Thirty steps on four triplets bring the loss well below its start and below the no-motion loss.

    (Measured: 0.074 at the start, 0.072 with no motion, 0.017 after 30 steps, 0.013 with GT.)
    """
    batch = {key: value[:TRIPLETS] for key, value in simcol_triplets().items()}
    cfg = Params().loss.replace(automask=False)
    start, no_motion, end = short_optimisation(batch, cfg, lambda *predicted: loss_with(batch, *predicted, cfg))
    assert end < 0.6 * start
    assert end < 0.6 * no_motion


def test_logged_losses_name_each_terms_share_of_the_total_and_its_unweighted_value():
    from endoflow.training.loop import logged_losses

    losses = {"total": 0.0315, "photometric": 0.03, "smoothness": 1.0, "kl": 50.0}
    logged = logged_losses(losses, {"photometric": 1.0, "smoothness": 1e-3, "kl": 1e-5})
    weighted = [value for key, value in logged.items() if key.startswith("loss/weighted/")]
    assert sum(weighted) == pytest.approx(logged["loss/total"])
    assert logged["loss/weighted/kl"] == pytest.approx(5e-4) and logged["loss/unweighted/kl"] == 50.0
    assert "loss/unweighted/photometric" not in logged  # weight 1: the same number twice would only confuse


def test_playing_triplets_backwards_swaps_their_neighbours_at_the_given_share():
    from endoflow.training.loop import played_backwards

    batch = simcol_triplets(size=32)
    assert played_backwards(batch, 0.0) is batch
    backwards = played_backwards(batch, 1.0)
    assert torch.equal(backwards["prev"], batch["next"]) and torch.equal(backwards["next"], batch["prev"])
    assert torch.equal(backwards["cur"], batch["cur"]) and torch.equal(backwards["K"], batch["K"])
    torch.manual_seed(3)
    some = played_backwards(batch, 0.5)
    swapped = [torch.equal(some["prev"][i], batch["next"][i]) for i in range(len(batch["cur"]))]
    assert 0 < sum(swapped) < len(swapped)
    torch.manual_seed(3)  # the global generator decides: a resumed run, its state restored, swaps the same ones
    again = played_backwards(batch, 0.5)
    assert torch.equal(again["prev"], some["prev"]) and torch.equal(again["next"], some["next"])


def test_a_triplet_played_backwards_is_explained_by_the_reversed_motion():
    """The exact poses of a reversed triplet are the forward ones swapped: the loss is the same, while the forward
    poses no longer fit it (the pose network has to see which way the camera went)."""
    from endoflow.training.loop import played_backwards

    batch = simcol_triplets()
    cfg = LossConfig(automask=False)
    forward = loss_with(batch, batch["depth"], batch["T_prev_cur"], batch["T_next_cur"], cfg)
    backwards = played_backwards(batch, 1.0)
    swapped = loss_with(backwards, batch["depth"], batch["T_next_cur"], batch["T_prev_cur"], cfg)
    assert swapped == pytest.approx(forward, rel=1e-6)
    assert loss_with(backwards, batch["depth"], batch["T_prev_cur"], batch["T_next_cur"], cfg) > 1.5 * forward


def circle_mask(size: int, radius_share: float = 0.45) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    return ((u - (size - 1) / 2) ** 2 + (v - (size - 1) / 2) ** 2 <= (radius_share * size) ** 2)[None, None]


def test_pixels_outside_the_field_of_view_give_no_gradient_to_depth():
    batch = simcol_triplets(size=32)
    valid = circle_mask(32).expand(len(batch["cur"]), 1, 32, 32)
    cfg = LossConfig()
    depth = batch["depth"].clone().requires_grad_(True)
    loss = reprojection(batch["cur"], [batch["prev"], batch["next"]], depth, [batch["T_prev_cur"], batch["T_next_cur"]],
                        batch["K"], cfg, valid=valid)
    loss.backward()
    assert depth.grad[~valid].abs().max() == 0 and depth.grad[valid].abs().sum() > 0
    disp = (1 / depth.detach()).requires_grad_(True)
    edge_aware_smoothness(disp, batch["cur"], valid).backward()
    assert disp.grad[~valid].abs().max() == 0 and disp.grad[valid].abs().sum() > 0


def test_the_geometry_term_gives_no_gradient_to_depth_outside_the_field_of_view():
    batch = simcol_triplets(size=32)
    valid = circle_mask(32).expand(len(batch["cur"]), 1, 32, 32)
    depth = (batch["depth"] * 1.1).requires_grad_(True)  # off the truth, so that it has a gradient
    sources = [batch["depth"] * 0.9, batch["depth"] * 1.05]
    geometry_consistency(depth, sources, [batch["T_prev_cur"], batch["T_next_cur"]], batch["K"], valid).backward()
    assert depth.grad[~valid].abs().max() == 0 and depth.grad[valid].abs().sum() > 0


def test_the_smoothness_of_every_scale_counts_inside_the_field_of_view_in_bfloat16_too():
    """Coarse scales find their mask by area averaging: in bfloat16 the threshold 0.999 would round to 1."""
    batch = simcol_triplets(size=64)
    params = Params()
    model = build_model(params, None).eval()
    masked = {**batch, "valid": circle_mask(64).expand(len(batch["cur"]), 1, 64, 64)}
    torch.manual_seed(0)
    full = training_step_losses(model, masked, params.loss)
    torch.manual_seed(0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        half = training_step_losses(model, masked, params.loss)
    for scale in range(4):
        assert float(half[f"smoothness/{scale}"]) == pytest.approx(float(full[f"smoothness/{scale}"]), rel=0.05)
        assert float(half[f"smoothness/{scale}"]) > 0


def test_the_held_out_photometric_error_ranks_the_true_depth_and_motion_first():
    batch = simcol_triplets()
    sources, truth = [batch["prev"], batch["next"]], [batch["T_prev_cur"], batch["T_next_cur"]]
    true = held_out_photometric_error(batch["cur"], sources, batch["depth"], truth, batch["K"])
    flat = held_out_photometric_error(batch["cur"], sources, torch.full_like(batch["depth"], float(
        batch["depth"].mean())), truth, batch["K"])
    still = held_out_photometric_error(batch["cur"], sources, batch["depth"], [torch.eye(4).expand_as(t) for t in truth],
                                       batch["K"])
    assert true.shape == (len(batch["cur"]),)
    assert (true < flat).all() and (true < still).all()
    # a frame rebuilt from itself has no error; outside the field of view nothing counts
    itself = held_out_photometric_error(batch["cur"], [batch["cur"]], batch["depth"], [torch.eye(4).expand_as(truth[0])],
                                        batch["K"])
    assert itself.abs().max() < 1e-5  # float32 round-off of the identity warp
    valid = circle_mask(SIZE).expand(len(batch["cur"]), 1, SIZE, SIZE)
    scrambled = {name: torch.where(valid, batch[name], torch.rand_like(batch[name])) for name in ("prev", "cur", "next")}
    inside = held_out_photometric_error(scrambled["cur"], [scrambled["prev"], scrambled["next"]], batch["depth"], truth,
                                        batch["K"], valid)
    unmasked = held_out_photometric_error(scrambled["cur"], [scrambled["prev"], scrambled["next"]], batch["depth"],
                                          truth, batch["K"])
    assert (inside < 0.5 * unmasked).all()


def test_the_best_epoch_is_picked_by_depth_where_validation_has_it_else_by_the_photometric_error():
    from endoflow.training.checkpoint import BestEpoch
    from endoflow.training.loop import improves_on, selection_metric

    labelled = {"val_abs_rel": 0.1, "val_rmse": 1.0, "val_photometric": 0.2}
    assert selection_metric(labelled) == "val_abs_rel" and selection_metric({"val_photometric": 0.2}) == "val_photometric"
    best = BestEpoch(0, labelled, {})
    assert improves_on({**labelled, "val_photometric": 0.3}, best)  # better depth wins, whatever the photometric
    assert not improves_on({**labelled, "val_abs_rel": 0.2, "val_photometric": 0.1}, best)
    unlabelled = BestEpoch(0, {"val_photometric": 0.2}, {})
    assert improves_on({"val_photometric": 0.19}, unlabelled) and not improves_on({"val_photometric": 0.21}, unlabelled)
    assert improves_on({}, BestEpoch(0, {}, {}))  # no validation data: the latest epoch


def test_a_field_of_view_that_is_everything_is_the_loss_without_one_to_the_bit():
    batch = simcol_triplets(size=32)
    params = Params()
    model = build_model(params, None).eval()
    torch.manual_seed(0)  # auto-masking's tie-break noise
    plain = training_step_losses(model, batch, params.loss)
    torch.manual_seed(0)
    everything = training_step_losses(model, {**batch, "valid": torch.ones_like(batch["depth"], dtype=torch.bool)},
                                      params.loss)
    assert torch.equal(plain["total"], everything["total"])


def test_frames_with_a_black_circular_border_and_its_mask_learn_depth_and_motion_inside_it():
    """The short optimisation above on the frames blacked out beyond a circle, with the field of view: scored on
    the original frames inside the circle, the loss falls as far as without a border."""
    batch = {key: value[:TRIPLETS] for key, value in simcol_triplets().items()}
    valid = circle_mask(SIZE).expand(TRIPLETS, 1, SIZE, SIZE)
    bordered = {**batch, **{name: batch[name] * valid for name in ("prev", "cur", "next")}, "valid": valid}
    cfg = Params().loss.replace(automask=False)

    def loss_inside(depth: torch.Tensor, T_prev: torch.Tensor, T_next: torch.Tensor) -> float:
        return reprojection(batch["cur"], [batch["prev"], batch["next"]], depth, [T_prev, T_next], batch["K"], cfg,
                            valid=valid).item()

    start, no_motion, end = short_optimisation(bordered, cfg, loss_inside)
    assert end < 0.6 * start
    assert end < 0.6 * no_motion


def differentiable_inputs(batch: dict) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """The batch's true depth and motion as leaves (motion as pose vectors), and the transforms they give."""
    from endoflow.geometry.pose import matrix_to_pose_vec

    depth = batch["depth"].clone().requires_grad_(True)
    vecs = torch.stack([matrix_to_pose_vec(batch[key]) for key in ("T_prev_cur", "T_next_cur")]).requires_grad_(True)
    return depth, vecs, [pose_vec_to_matrix(vecs[0]), pose_vec_to_matrix(vecs[1])]


def gradients_of(term: Callable[[torch.Tensor, list[torch.Tensor]], torch.Tensor], batch: dict
                 ) -> tuple[float, torch.Tensor, torch.Tensor]:
    depth, vecs, transforms = differentiable_inputs(batch)
    torch.manual_seed(0)  # auto-masking's tie-break noise
    loss = term(depth, transforms)
    loss.backward()
    return float(loss.detach()), depth.grad, vecs.grad


def test_without_the_mask_on_the_pose_the_depth_learns_from_the_masked_loss_and_the_pose_from_the_unmasked():
    batch = simcol_triplets(size=32)
    sources = [batch["prev"], batch["next"]]
    masked_cfg, split_cfg = LossConfig(), LossConfig(automask_pose=False)
    unmasked_cfg = LossConfig(automask=False)

    def term(cfg: LossConfig):
        return lambda depth, transforms: reprojection(batch["cur"], sources, depth, transforms, batch["K"], cfg)

    masked, split, unmasked = (gradients_of(term(cfg), batch) for cfg in (masked_cfg, split_cfg, unmasked_cfg))
    assert split[0] == masked[0]  # the value logged is the masked loss's, so that runs compare
    assert torch.equal(split[1], masked[1])  # the depth's gradient: the mask's
    assert torch.allclose(split[2], unmasked[2], rtol=1e-5, atol=1e-9)  # the pose's: every pixel's
    assert not torch.allclose(masked[2], unmasked[2], rtol=1e-2)  # the mask does change it on these frames
    # the option means nothing without the mask: the same loss and gradients as the unmasked one
    plain = gradients_of(term(LossConfig(automask=False, automask_pose=False)), batch)
    assert plain[0] == unmasked[0] and torch.equal(plain[1], unmasked[1]) and torch.equal(plain[2], unmasked[2])


def test_with_the_mask_on_the_pose_alone_the_depth_learns_from_the_unmasked_loss_and_the_pose_from_the_masked():
    batch = simcol_triplets(size=32)
    sources = [batch["prev"], batch["next"]]

    def term(cfg: LossConfig):
        return lambda depth, transforms: reprojection(batch["cur"], sources, depth, transforms, batch["K"], cfg)

    masked, pose_only, unmasked = (gradients_of(term(cfg), batch) for cfg in (
        LossConfig(), LossConfig(automask_depth=False), LossConfig(automask=False)))
    assert pose_only[0] == masked[0]  # the value logged is the masked loss's
    assert torch.equal(pose_only[2], masked[2])  # the pose's gradient: the mask's
    assert torch.allclose(pose_only[1], unmasked[1], rtol=1e-5, atol=1e-9)  # the depth's: every pixel's
    assert not torch.allclose(masked[1], unmasked[1], rtol=1e-2)  # the mask does change it on these frames


def test_with_the_mask_on_the_pose_alone_a_learned_K_learns_with_the_depth_from_every_pixel():
    batch = simcol_triplets(size=32)
    sources = [batch["prev"], batch["next"]]

    def K_gradient(cfg: LossConfig) -> torch.Tensor:
        K = batch["K"].clone().requires_grad_(True)
        depth, _, transforms = differentiable_inputs(batch)
        torch.manual_seed(0)
        reprojection(batch["cur"], sources, depth, transforms, K, cfg).backward()
        return K.grad

    pose_only, unmasked = K_gradient(LossConfig(automask_depth=False)), K_gradient(LossConfig(automask=False))
    assert torch.allclose(pose_only, unmasked, rtol=1e-5, atol=1e-9)
    assert not torch.allclose(K_gradient(LossConfig()), unmasked, rtol=1e-2)


def test_a_forward_answer_for_a_paused_camera_is_pulled_back_only_where_the_mask_spares_the_pose():
    """The camera stops (each neighbour is the target itself) and the pose answers the true forward step. The
    unwarped neighbours explain every pixel, so auto-masking leaves the pose nothing but its tie-break noise;
    without the mask on the pose, a step against the gradient shortens the forward answer."""
    batch = simcol_triplets(size=32)
    paused = {**batch, "prev": batch["cur"], "next": batch["cur"]}
    sources = [paused["cur"], paused["cur"]]

    def pose_gradient(cfg: LossConfig) -> torch.Tensor:
        term = lambda depth, transforms: reprojection(paused["cur"], sources, depth, transforms, paused["K"], cfg)
        return gradients_of(term, paused)[2]

    masked, split = pose_gradient(LossConfig()), pose_gradient(LossConfig(automask_pose=False))
    assert masked.abs().max() < 1e-3 * split.abs().max()
    _, vecs, _ = differentiable_inputs(paused)
    forward = vecs.detach()[..., 3:]
    stepped = forward - 1e-3 * split[..., 3:] / split[..., 3:].norm()
    assert stepped.norm() < forward.norm()


def test_training_without_the_mask_on_the_pose_changes_the_pose_networks_gradient_and_not_the_depth_networks():
    batch = {key: value[:2] for key, value in simcol_triplets(size=32).items()}
    batch["valid"] = circle_mask(32).expand(2, 1, 32, 32)  # inside a field of view, as real video trains
    params = Params()
    torch.manual_seed(0)
    model = build_model(params, None)

    def gradients(cfg: LossConfig) -> dict[str, torch.Tensor]:
        model.zero_grad(set_to_none=True)
        torch.manual_seed(1)  # the pose VAE's samples and auto-masking's tie-break noise
        training_step_losses(model, batch, cfg)["total"].backward()
        return {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}

    masked, split = gradients(params.loss), gradients(params.loss.replace(automask_pose=False))
    depth = [name for name in masked if name.startswith("depth_net.")]
    pose = [name for name in masked if name.startswith("pose_net.")]
    assert depth and pose and set(split) == set(masked)
    assert all(torch.allclose(split[name], masked[name], rtol=1e-4, atol=1e-10) for name in depth)
    assert not all(torch.allclose(split[name], masked[name], rtol=1e-2) for name in pose)


def test_training_with_the_mask_on_the_pose_alone_changes_the_depth_networks_gradient_and_not_the_pose_networks():
    batch = {key: value[:2] for key, value in simcol_triplets(size=32).items()}
    batch["valid"] = circle_mask(32).expand(2, 1, 32, 32)
    params = Params()
    torch.manual_seed(0)
    model = build_model(params, None)
    totals: list[float] = []
    masked = step_gradients(model, batch, params.loss, totals)
    pose_only = step_gradients(model, batch, params.loss.replace(automask_depth=False), totals)
    assert totals[0] == totals[1] and set(pose_only) == set(masked)
    assert any(name.startswith("depth_net.") for name in masked)
    assert same_gradients(pose_only, masked, "pose_net.")
    assert not same_gradients(pose_only, masked, "depth_net.")


def step_gradients(model: torch.nn.Module, batch: dict, cfg: LossConfig, totals: list[float]
                   ) -> dict[str, torch.Tensor]:
    """Each parameter's gradient of one training step's total (appended to ``totals``), from seed 1: the pose
    VAE's samples and auto-masking's tie-break noise."""
    model.zero_grad(set_to_none=True)
    torch.manual_seed(1)
    total = training_step_losses(model, batch, cfg)["total"]
    total.backward()
    totals.append(total.item())
    return {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}


def same_gradients(a: dict, b: dict, prefix: str) -> bool:
    """The gradients of the parameters named ``prefix...`` agree (there are some)."""
    names = [name for name in a if name.startswith(prefix)]
    return bool(names) and all(torch.allclose(a[n], b[n], rtol=1e-4, atol=1e-10) for n in names)


def test_with_the_spread_kept_under_the_mask_the_pose_mean_learns_from_every_pixel_and_its_spread_from_the_mask():
    """``automask_pose_spread``: the variance head's gradient is the masked loss's (as with the mask on the pose),
    the mean head's is that of every pixel (as without it), and the depth network's stays the mask's."""
    batch = {key: value[:2] for key, value in simcol_triplets(size=32).items()}
    params = Params()
    torch.manual_seed(0)
    model = build_model(params, None)
    with torch.no_grad():
        model.pose_net.logvar_head.bias.fill_(-8.0)  # a spread whose samples move pixels

    totals: list[float] = []

    def gradients(cfg: LossConfig) -> dict[str, torch.Tensor]:
        return step_gradients(model, batch, cfg, totals)

    masked = gradients(params.loss)
    split = gradients(params.loss.replace(automask_pose=False))
    spread = gradients(params.loss.replace(automask_pose=False, automask_pose_spread=True))
    assert totals[0] == totals[1] == totals[2]  # the masked loss's value, whichever part learns from it

    spread_head, mean_head = "pose_net.logvar_head.", "pose_net.mean_head."
    assert same_gradients(spread, masked, spread_head) and not same_gradients(split, masked, spread_head)
    assert same_gradients(spread, split, mean_head) and not same_gradients(masked, split, mean_head)
    assert same_gradients(spread, masked, "depth_net.")
    # without the mask on the pose switched off, the key changes nothing
    assert all(torch.equal(v, masked[n]) for n, v in gradients(params.loss.replace(automask_pose_spread=True)).items())


def test_the_poses_own_ssim_share_changes_the_pose_networks_gradient_alone():
    """``pose_ssim_weight`` with ``automask_pose`` false: the pose network's gradient is that of the unmasked loss
    at that SSIM share, the depth network's stays the masked loss's at ``ssim_weight``, the logged loss is the
    masked one; null means ``ssim_weight``, and with the mask on the pose the key changes nothing."""
    batch = {key: value[:2] for key, value in simcol_triplets(size=32).items()}
    params = Params()
    torch.manual_seed(0)
    model = build_model(params, None)
    totals: list[float] = []

    def gradients(cfg: LossConfig) -> dict[str, torch.Tensor]:
        return step_gradients(model, batch, cfg, totals)

    split = params.loss.replace(automask_pose=False)
    default = gradients(split)
    l1_pose = gradients(split.replace(pose_ssim_weight=0.0))
    l1_all = gradients(split.replace(ssim_weight=0.0))
    assert totals[0] == totals[1] != totals[2]  # the masked loss's value, at ssim_weight

    assert same_gradients(l1_pose, default, "depth_net.") and not same_gradients(l1_all, default, "depth_net.")
    assert same_gradients(l1_pose, l1_all, "pose_net.") and not same_gradients(default, l1_all, "pose_net.")
    explicit = gradients(split.replace(pose_ssim_weight=split.ssim_weight))
    assert all(torch.equal(v, default[n]) for n, v in explicit.items())
    masked = gradients(params.loss)
    assert all(torch.equal(v, masked[n]) for n, v in gradients(params.loss.replace(pose_ssim_weight=0.0)).items())
