"""Models: generator and critic shapes, the frozen latent bank inside DepthNet, PoseNet's VAE, summaries."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from endoflow.cli import main as cli_main
from endoflow.config import Params, load_params
from endoflow.errors import DataFormatError
from endoflow.geometry.pose import invert_pose, pose_vec_to_matrix
from endoflow.models.critic import Critic
from endoflow.models.edge_padding import EdgePaddedConv2d, edge_pad, sliced_edge_pad
from endoflow.models.endoflow_model import build_model
from endoflow.models.gemm_weight_grad import FEW_POSITIONS, GemmWeightGradConv2d, conv_weight_grad_by_gemm
from endoflow.models.latent_bank import (
    GeneratorSpec,
    InitScaledConv2d,
    LatentBankGenerator,
    generator_payload,
    load_generator,
)
from endoflow.models.resnet_encoder import ResNetEncoder
from endoflow.models.summary import RELEASED_CODE_MILLIONS, model_summary
from endoflow.training import objective
from endoflow.training.objective import training_step_losses

PAPER_PRESET = Path(__file__).resolve().parents[1] / "presets" / "paper.yaml"
SPEC = GeneratorSpec(resolution=32, start_resolution=4, latent_dim=16, style_dim=16, mapping_layers=2,
                     channel_base=128, channel_max=32, conv_init_scale=1.0)


def small_params(**model) -> Params:
    params = Params()
    cfg = params.latent_bank
    cfg.resolution, cfg.start_resolution, cfg.latent_dim, cfg.style_dim = 32, 4, 16, 16
    cfg.mapping_layers, cfg.channel_base, cfg.channel_max = 2, 128, 32
    for key, value in model.items():
        setattr(params.model, key, value)
    return params


def random_batch(batch: int, height: int, width: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[0.8 * width, 0, width / 2], [0, 0.8 * width, height / 2], [0, 0, 1.0]])
    return {
        "prev": torch.rand(batch, 3, height, width, generator=g),
        "cur": torch.rand(batch, 3, height, width, generator=g),
        "next": torch.rand(batch, 3, height, width, generator=g),
        "K": K.expand(batch, 3, 3).clone(),
    }


# ---------------------------------------------------------------------------------- generator, critic
@pytest.mark.parametrize("resolution", SPEC.resolutions)
def test_generator_and_critic_work_at_every_growing_resolution(resolution):
    generator, critic = LatentBankGenerator(SPEC), Critic(SPEC)
    for alpha in (0.0, 0.5, 1.0):
        maps = generator(torch.randn(4, SPEC.latent_dim), resolution, alpha)
        assert maps.shape == (4, 1, resolution, resolution)
        assert critic(maps, resolution, alpha).shape == (4,)


def test_fresh_critic_has_a_usable_input_gradient_at_full_resolution():
    """The gradient penalty targets norm 1; a fresh critic far below it would lag the generator."""
    critic = Critic(SPEC)
    maps = (0.3 * torch.randn(8, 1, SPEC.resolution, SPEC.resolution)).requires_grad_()
    (gradient,) = torch.autograd.grad(critic(maps).sum(), maps)
    assert gradient.flatten(1).norm(dim=1).mean() > 0.05


def test_fade_in_at_alpha_zero_is_the_upsampled_previous_resolution():
    generator = LatentBankGenerator(SPEC)
    z = torch.randn(3, SPEC.latent_dim)
    torch.manual_seed(5)
    faded = generator(z, 16, alpha=0.0)
    torch.manual_seed(5)
    coarse = generator(z, 8, alpha=1.0)
    torch.testing.assert_close(faded, torch.nn.functional.interpolate(coarse, scale_factor=2, mode="nearest"))


def test_generator_noise_injection_and_styles_both_shape_the_output():
    generator = LatentBankGenerator(SPEC)
    for block in generator.blocks:
        for noise in block.noises:
            torch.nn.init.constant_(noise.strength, 0.5)
        for adain in block.adains:
            torch.nn.init.normal_(adain.affine.weight, std=0.3)
    z = torch.randn(2, SPEC.latent_dim)
    same_z = [generator(z) for _ in range(2)]
    assert not torch.allclose(*same_z)  # fresh per-pixel noise each call
    with torch.no_grad():
        for block in generator.blocks:
            for noise in block.noises:
                noise.strength.zero_()
    assert torch.allclose(generator(z), generator(z))
    assert not torch.allclose(generator(z), generator(torch.randn(2, SPEC.latent_dim)))


def generator_with_conv_init_scale(scale: float, seed: int = 0) -> LatentBankGenerator:
    torch.manual_seed(seed)
    return LatentBankGenerator(replace(SPEC, conv_init_scale=scale))


def test_shrunk_synthesis_convolutions_keep_a_fresh_generator_and_turn_faster_under_adam():
    default, shrunk = generator_with_conv_init_scale(1.0), generator_with_conv_init_scale(0.25)
    z = torch.randn(4, SPEC.latent_dim)
    # AdaIN follows every shrunk convolution; only its epsilon tells the two apart.
    assert (shrunk(z) - default(z)).norm() < 0.05 * default(z).norm()
    for block, default_block in zip(shrunk.blocks, default.blocks):  # the same draw, scaled
        for conv, default_conv in ((block.up, default_block.up), (block.conv, default_block.conv)):
            if conv is not None:
                assert torch.equal(conv.weight, 0.25 * default_conv.weight)
                assert torch.equal(conv.bias, 0.25 * default_conv.bias)
    assert torch.equal(shrunk.to_depth[-1].weight, default.to_depth[-1].weight)  # not scale-free: untouched

    def relative_change_after_one_adam_step(generator: LatentBankGenerator) -> float:
        weight = generator.blocks[-1].conv.weight
        before = weight.detach().clone()
        optimiser = torch.optim.Adam(generator.parameters(), lr=1e-4, betas=(0.0, 0.99))
        generator(z).square().mean().backward()
        optimiser.step()
        return ((weight.detach() - before).norm() / before.norm()).item()

    ratio = relative_change_after_one_adam_step(shrunk) / relative_change_after_one_adam_step(default)
    assert ratio == pytest.approx(4.0, rel=0.05)


def test_the_init_scale_is_recorded_in_the_state_dict_and_survives_a_save_and_load(tmp_path):
    shrunk = generator_with_conv_init_scale(0.25)
    recorded = {k: v for k, v in shrunk.state_dict().items() if k.endswith("init_scale")}
    assert set(recorded) == {f"blocks.{i}.{name}.init_scale" for i in range(len(SPEC.resolutions))
                             for name in (("up", "conv") if i else ("conv",))}
    assert all(value.item() == 0.25 for value in recorded.values())
    path = tmp_path / "bank.pt"
    torch.save(generator_payload(shrunk), path)
    loaded = load_generator(path)
    assert loaded.spec.conv_init_scale == 0.25
    assert loaded.blocks[-1].conv.init_scale.item() == 0.25


def test_reinitialising_an_init_scaled_convolution_keeps_its_scale():
    torch.manual_seed(3)
    shrunk = InitScaledConv2d(2, 64, 3, init_scale=0.25)
    torch.manual_seed(3)
    default = torch.nn.Conv2d(2, 64, 3)
    assert torch.equal(shrunk.weight, 0.25 * default.weight) and torch.equal(shrunk.bias, 0.25 * default.bias)
    shrunk.reset_parameters()
    bound = 0.25 / (2 * 3 * 3) ** 0.5  # PyTorch's default is uniform within 1 / sqrt(fan_in) (weight and bias)
    assert shrunk.weight.abs().max() <= bound and shrunk.weight.abs().max() > 0.9 * bound
    assert shrunk.bias.abs().max() <= bound


def test_bank_features_follow_any_grid_and_reject_mismatched_styles():
    generator = LatentBankGenerator(SPEC)
    adains = [list(block.adains) for block in generator.blocks]
    styles = [torch.randn(2, SPEC.style_dim, 3 * 2**k, 5 * 2**k) for k in range(len(generator.blocks))]
    features = generator.bank_features(styles, adains)
    assert [tuple(f.shape) for f in features] == [
        (2, c, 3 * 2**k, 5 * 2**k) for k, c in enumerate(generator.block_channels)
    ]
    with pytest.raises(ValueError, match="styles\\[1\\]"):
        generator.bank_features([styles[0], styles[0]], adains[:2])


def test_saved_generator_loads_with_weights_only(tmp_path):
    generator = LatentBankGenerator(SPEC)
    path = tmp_path / "bank.pt"
    torch.save(generator_payload(generator), path)
    loaded = load_generator(str(path))
    assert loaded.spec == SPEC
    for name, tensor in generator.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[name], tensor)
    torch.save({"something": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(DataFormatError):
        load_generator(str(tmp_path / "other.pt"))


# ------------------------------------------------------------------------------------------ DepthNet
@pytest.mark.parametrize("latent_bank", [True, False])
@pytest.mark.parametrize("size", [(64, 64), (96, 160)])
def test_depth_net_gives_four_sigmoid_disparities_for_sizes_divisible_by_32(latent_bank, size):
    model = build_model(small_params(latent_bank=latent_bank), None)
    rgb = torch.rand(2, 3, *size)
    disps = model.depth_net(rgb)
    assert [tuple(d.shape) for d in disps] == [(2, 1, size[0] // 2**s, size[1] // 2**s) for s in range(4)]
    assert all(((d > 0) & (d < 1)).all() for d in disps)
    depth = model.predict_depth(rgb)
    assert depth.shape == (2, 1, *size)
    assert depth.min() >= model.cfg.min_depth and depth.max() <= model.cfg.max_depth


def test_depth_net_rejects_sizes_not_divisible_by_32():
    model = build_model(small_params(latent_bank=False), None)
    with pytest.raises(ValueError, match="divisible by 32"):
        model.depth_net(torch.rand(1, 3, 48, 64))


def test_disparity_maps_linearly_to_inverse_depth_between_the_bounds():
    model = build_model(small_params(latent_bank=False), None)
    depth = model.disp_to_depth(torch.tensor([0.0, 0.5, 1.0]))
    min_d, max_d = model.cfg.min_depth, model.cfg.max_depth
    torch.testing.assert_close(depth[0], torch.tensor(max_d))
    torch.testing.assert_close(depth[2], torch.tensor(min_d))
    torch.testing.assert_close(1 / depth[1], torch.tensor(0.5 / min_d + 0.5 / max_d))


def test_frozen_bank_stays_fixed_while_adapters_encoder_and_decoder_learn():
    params = small_params(latent_bank=True)
    model = build_model(params, None).train()
    depth_net = model.depth_net
    groups = {
        "bank": dict(depth_net.bank.named_parameters()),
        "adain": dict(depth_net.adapters.adains.named_parameters()),
        "style": dict(depth_net.adapters.styles.named_parameters()),
        "encoder": dict(depth_net.encoder.named_parameters()),
        "decoder": dict(depth_net.decoder.named_parameters()),
    }
    before = {g: {n: p.detach().clone() for n, p in ps.items()} for g, ps in groups.items()}
    assert not any(p.requires_grad for p in groups["bank"].values())
    # Everything goes to the optimiser, as a careless training loop would do: frozen weights get no gradient.
    optimiser = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-2)
    batch = random_batch(2, 64, 64)  # the bank's coarsest map needs more than one pixel to normalise
    # Two steps: the zero-initialised AdaIN affines must move before gradients reach the style layers.
    for _ in range(2):
        optimiser.zero_grad()
        training_step_losses(model, batch, params.loss)["total"].backward()
        optimiser.step()

    def changed(group: str) -> bool:
        return any(not torch.equal(before[group][n], p) for n, p in groups[group].items())

    assert not changed("bank")
    assert changed("adain") and changed("style") and changed("encoder") and changed("decoder")
    assert all(not p.requires_grad for p in model.depth_net.bank.parameters())


def test_bank_mode_uses_the_bank_features_in_the_decoder():
    model = build_model(small_params(latent_bank=True), None).eval()
    rgb = torch.rand(1, 3, 64, 64)
    before = model.depth_net(rgb)[0]
    with torch.no_grad():
        model.depth_net.bank.const.copy_(torch.randn_like(model.depth_net.bank.const))
    assert not torch.allclose(before, model.depth_net(rgb)[0])


# ------------------------------------------------------------------------------------------- PoseNet
def test_pose_net_starts_near_identity_with_small_spread():
    model = build_model(small_params(latent_bank=False), None).eval()
    batch = random_batch(2, 32, 32)
    mean, logvar = model.pose_net(batch["cur"], batch["next"])
    assert mean.shape == logvar.shape == (2, 6)
    assert mean.abs().max() < 0.05
    torch.testing.assert_close(logvar, torch.full_like(logvar, model.cfg.pose_logvar_init), atol=0.1, rtol=0)


def test_gradients_reach_both_pose_heads():
    params = small_params(latent_bank=False)
    model = build_model(params, None).train()
    training_step_losses(model, random_batch(2, 32, 32), params.loss)["total"].backward()
    for head in (model.pose_net.mean_head, model.pose_net.logvar_head):
        assert head.weight.grad is not None and head.weight.grad.abs().sum() > 0


def test_deterministic_pose_net_without_vae():
    params = small_params(latent_bank=False, pose_vae=False)
    model = build_model(params, None).train()
    batch = random_batch(2, 32, 32)
    estimate = model.source_pose(batch["cur"], batch["next"], source_is_next=True)
    assert estimate.logvar is None and torch.equal(estimate.vec, estimate.mean)
    assert training_step_losses(model, batch, params.loss)["kl"] == 0


def test_without_pose_sampling_training_warps_with_the_mean_and_keeps_the_kl():
    params = small_params(latent_bank=False, pose_sample=False)
    model = build_model(params, None).train()
    with torch.no_grad():
        model.pose_net.logvar_head.bias.fill_(-2.0)  # a spread a sample would show
    batch = random_batch(2, 32, 32)
    estimate = model.source_pose(batch["cur"], batch["next"], source_is_next=True)
    assert estimate.logvar is not None and torch.equal(estimate.vec, estimate.mean)
    losses = training_step_losses(model, batch, params.loss)
    assert losses["kl"] > 0
    losses["total"].backward()
    assert model.pose_net.logvar_head.weight.grad.abs().sum() > 0  # the KL alone trains the variance head


@pytest.mark.parametrize("source_is_next", [True, False])
def test_a_samples_spread_and_mean_parts_are_its_pose_each_passing_one_gradient(source_is_next):
    model = build_model(small_params(latent_bank=False), None).train()
    with torch.no_grad():
        model.pose_net.logvar_head.bias.fill_(-2.0)  # a spread large enough to see
    batch = random_batch(2, 32, 32)
    pose = model.source_pose(batch["cur"], batch["next"], source_is_next=source_is_next)
    spread, mean = pose.spread_and_mean_parts()
    assert torch.equal(spread, pose.T_source_target) and torch.equal(mean, pose.T_source_target)
    heads = (model.pose_net.mean_head.weight, model.pose_net.logvar_head.weight)
    through_spread = torch.autograd.grad(spread.sum(), heads, allow_unused=True, retain_graph=True)
    through_mean = torch.autograd.grad(mean.sum(), heads, allow_unused=True)
    reached = [[g is not None and bool(g.abs().sum() > 0) for g in grads] for grads in (through_spread, through_mean)]
    assert reached == [[False, True], [True, False]]  # (mean head, variance head) through each part


def test_previous_frame_pose_is_the_inverse_of_the_forward_motion():
    model = build_model(small_params(latent_bank=False), None).eval()
    batch = random_batch(2, 32, 32)
    with torch.no_grad():
        model.pose_net.mean_head.weight.normal_(std=1.0)  # motions large enough to tell directions apart
    forward = model.predict_pose(batch["prev"], batch["cur"])  # T_cur_prev: cur is the later frame
    backward = model.predict_pose(batch["cur"], batch["prev"], source_is_next=False)  # T_prev_cur
    torch.testing.assert_close(backward, invert_pose(forward))
    estimate = model.source_pose(batch["cur"], batch["prev"], source_is_next=False)
    torch.testing.assert_close(estimate.T_source_target, invert_pose(pose_vec_to_matrix(estimate.mean)))


@pytest.mark.parametrize("training", [True, False])
def test_warp_uses_the_sampled_pose_in_training_and_the_mean_in_evaluation(monkeypatch, training):
    params = small_params(latent_bank=False)
    model = build_model(params, None).train(training)
    with torch.no_grad():
        model.pose_net.logvar_head.bias.fill_(-2.0)  # visible spread
    estimates, used = [], []
    source_pose = model.source_pose
    warp = objective.warp_frame

    def recording_source_pose(*args, **kwargs):
        estimates.append(source_pose(*args, **kwargs))
        return estimates[-1]

    def recording_warp(image, depth, T, K):
        used.append(T)
        return warp(image, depth, T, K)

    monkeypatch.setattr(model, "source_pose", recording_source_pose)
    monkeypatch.setattr(objective, "warp_frame", recording_warp)
    training_step_losses(model, random_batch(2, 32, 32), params.loss)
    prev, nxt = estimates
    assert len(used) == 2 * 4  # two sources at each of the four scales
    for i, T in enumerate(used):
        torch.testing.assert_close(T, (prev if i % 2 == 0 else nxt).T_source_target)
    torch.testing.assert_close(nxt.T_source_target, pose_vec_to_matrix(nxt.vec))
    torch.testing.assert_close(prev.T_source_target, invert_pose(pose_vec_to_matrix(prev.vec)))
    for estimate in estimates:
        assert torch.equal(estimate.vec, estimate.mean) != training


# ----------------------------------------------------------------------------------- encoder weights
def test_local_resnet_weights_load_into_depth_and_pose_encoders(tmp_path):
    source = ResNetEncoder()
    state = {**source.state_dict(), "fc.weight": torch.zeros(1000, 512), "fc.bias": torch.zeros(1000)}
    path = tmp_path / "resnet18.pt"
    torch.save(state, path)
    single, pair = ResNetEncoder(weights=str(path)), ResNetEncoder(num_images=2, weights=str(path))
    torch.testing.assert_close(single.layer3[0].conv1.weight, source.layer3[0].conv1.weight)
    torch.testing.assert_close(pair.conv1.weight, source.conv1.weight.repeat(1, 2, 1, 1) / 2)
    torch.save({"conv1.weight": torch.zeros(3)}, tmp_path / "bad.pt")
    with pytest.raises(DataFormatError):
        ResNetEncoder(weights=str(tmp_path / "bad.pt"))


# ------------------------------------------------------------------------------------------- summary
def test_summary_counts_frozen_bank_and_new_adapters_separately():
    full = model_summary(small_params())
    plain = model_summary(small_params(latent_bank=False))
    assert full["latent_bank"]["trainable"] == 0 and full["latent_bank"]["frozen"] > 0
    assert full["bank_adapters"]["trainable"] > 0
    for component in ("latent_bank", "bank_adapters"):
        assert (plain[component]["trainable"], plain[component]["frozen"]) == (0, 0)
    assert full["encoder"] == plain["encoder"] and full["pose_net"] == plain["pose_net"]
    assert full["decoder"]["trainable"] > plain["decoder"]["trainable"]  # extra [h, a] input channels
    assert full["total"]["frozen"] == full["latent_bank"]["frozen"]


def test_model_summary_cli_prints_json(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text("model:\n  latent_bank: false\n")
    assert cli_main(["model", "summary", "--set", "model.pose_vae=false", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report["pose_net"]) == {"trainable", "frozen", "released_code_millions"}
    assert report["latent_bank"]["frozen"] == 0
    assert report["latent_bank"]["released_code_millions"] == 75.8  # the released code's bank is there anyway
    assert report["bank_adapters"]["released_code_millions"] is None  # no figure: none is made up


def test_model_summary_text_puts_the_released_code_beside_ours(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text("model:\n  latent_bank: false\n")
    assert cli_main(["model", "summary"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[-3:] == ["released", "code", "(M)"]
    rows = {line.split()[0]: line.split()[1:] for line in lines[1:7]}
    assert rows["pose_net"][-1] == f"{RELEASED_CODE_MILLIONS['pose_net']:.1f}"
    assert rows["latent_bank"][-2:] == ["0.0", "75.8"]
    assert rows["bank_adapters"][-1] == "-"
    assert "released code" in lines[-1]  # the figures' source


# ------------------------------------------------------------------------------------------ paper preset
def test_the_paper_preset_bank_has_the_released_codes_scale_and_works_at_480():
    """The shapes and the bank scale the paper preset claims, on the model it builds, at the paper's 480x480.

    On the meta device (shapes without arithmetic, about 2 s): a real 480-px pass costs 513 GFLOP, several seconds
    on 2 cores. tests/test_paper_dry_run.py trains and evaluates the same model for real."""
    params = load_params(PAPER_PRESET)
    with torch.device("meta"):
        model = build_model(params, latent_bank_path=None).eval()
        bank_maps = []
        for block in model.depth_net.bank.blocks:
            block.register_forward_hook(lambda module, inputs, output: bank_maps.append(tuple(output.shape)))
        disps = model.depth_net(torch.rand(1, 3, 480, 480))
        frozen = model_summary(params)["latent_bank"]["frozen"]
    assert [tuple(d.shape) for d in disps] == [(1, 1, 480 // 2**s, 480 // 2**s) for s in range(4)]
    assert bank_maps == [(1, c, 15 * 2**k, 15 * 2**k) for k, c in enumerate((1024, 1024, 1024, 512, 256))]
    assert abs(frozen / (RELEASED_CODE_MILLIONS["latent_bank"] * 1e6) - 1) < 0.1  # 79.8 M against 75.8 M


@pytest.mark.parametrize("width", [1, 2])
def test_edge_padding_is_replicate_padding_to_the_bit_in_values_and_to_rounding_in_gradients(width: int) -> None:
    g = torch.Generator().manual_seed(width)
    x = torch.randn(2, 5, 7, 9, dtype=torch.float64, generator=g).requires_grad_()
    padded, reference = sliced_edge_pad(x, width), F.pad(x, (width,) * 4, mode="replicate")
    assert torch.equal(padded, reference)
    upstream = torch.randn(reference.shape, dtype=torch.float64, generator=g)
    # a corner's gradient sums (width + 1)^2 upstream values in another order than torch's: equal to rounding (over
    # 600 unseeded draws they differed by up to 2.7e-15, and the former 1e-15 failed with some seeds' draws)
    assert torch.allclose(torch.autograd.grad(padded, x, upstream)[0], torch.autograd.grad(reference, x, upstream)[0],
                          rtol=0, atol=1e-13)
    assert torch.equal(sliced_edge_pad(x.to(memory_format=torch.channels_last), width), reference)
    assert torch.equal(edge_pad(x, width), reference)


def test_an_edge_padded_convolution_is_a_replicate_padded_one_with_the_same_weights_and_names() -> None:
    ours = EdgePaddedConv2d(5, 4, 3)
    theirs = nn.Conv2d(5, 4, 3, padding=1, padding_mode="replicate")
    theirs.load_state_dict(ours.state_dict())  # the same names: model files of either load into the other
    x = torch.randn(2, 5, 6, 7)
    assert torch.allclose(ours(x), theirs(x), atol=1e-6)
    with pytest.raises(ValueError, match="odd"):
        EdgePaddedConv2d(5, 4, 2)


@pytest.mark.parametrize("kernel, stride, size", [(3, 1, 2), (3, 2, 4), (1, 1, 2), (7, 2, 9), (3, 1, 5)])
def test_the_weight_gradient_as_one_matrix_product_is_torchs(kernel: int, stride: int, size: int) -> None:
    x = torch.randn(3, 5, size, size, dtype=torch.float64)
    weight = torch.randn(4, 5, kernel, kernel, dtype=torch.float64)
    grad_out = torch.randn_like(F.conv2d(x, weight, stride=stride, padding=kernel // 2))
    ours = conv_weight_grad_by_gemm(x, grad_out, weight.shape, (stride, stride), (kernel // 2, kernel // 2))
    torchs = torch.nn.grad.conv2d_weight(x, weight.shape, grad_out, stride, kernel // 2)
    assert torch.allclose(ours, torchs, rtol=0, atol=1e-12)


def test_a_gemm_weight_grad_convolution_is_nn_conv2d_in_output_names_and_gradients() -> None:
    ours = GemmWeightGradConv2d(64, 32, 3, padding=1)
    theirs = nn.Conv2d(64, 32, 3, padding=1)
    theirs.load_state_dict(ours.state_dict())
    x = torch.randn(6, 64, 2, 2, requires_grad=True)
    assert ours._takes_gemm_weight_grad(x, ours.weight)
    y_ours, y_theirs = ours(x), theirs(x)
    assert torch.equal(y_ours, y_theirs)  # the forward pass is torch's own
    upstream = torch.randn_like(y_ours)
    grads_ours = torch.autograd.grad(y_ours, [x, ours.weight, ours.bias], upstream)
    grads_theirs = torch.autograd.grad(y_theirs, [x, theirs.weight, theirs.bias], upstream)
    for a, b in zip(grads_ours, grads_theirs):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-5)


def test_a_gemm_weight_grad_convolution_leaves_other_cases_to_torch() -> None:
    conv = GemmWeightGradConv2d(8, 8, 3, padding=1)
    few, many = torch.randn(2, 8, 2, 2), torch.randn(2, 8, 3, 3)
    assert conv._takes_gemm_weight_grad(few, conv.weight) and 3 * 3 > FEW_POSITIONS
    assert not conv._takes_gemm_weight_grad(many, conv.weight)
    with torch.no_grad():
        assert not conv._takes_gemm_weight_grad(few, conv.weight)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not conv._takes_gemm_weight_grad(few, conv.weight)
    frozen = GemmWeightGradConv2d(8, 8, 3, padding=1).requires_grad_(False)
    assert not frozen._takes_gemm_weight_grad(few, frozen.weight)
    grouped = GemmWeightGradConv2d(8, 8, 3, padding=1, groups=2)
    assert not grouped._takes_gemm_weight_grad(few, grouped.weight)
