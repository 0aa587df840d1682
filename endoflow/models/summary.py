"""Trainable and frozen parameter counts per component of the model that the params describe."""

from __future__ import annotations

from torch import nn

from endoflow.config import Params
from endoflow.models.endoflow_model import build_model

COMPONENTS = ("encoder", "latent_bank", "bank_adapters", "decoder", "pose_net")


def _counts(module: nn.Module | None) -> dict[str, int]:
    params = list(module.parameters()) if module is not None else []
    return {
        "trainable": sum(p.numel() for p in params if p.requires_grad),
        "frozen": sum(p.numel() for p in params if not p.requires_grad),
    }


def model_summary(params: Params) -> dict[str, dict[str, int]]:
    """``{component: {"trainable": n, "frozen": n}}`` for each of :data:`COMPONENTS`, plus ``total``.

    The latent bank is counted with the ``params.latent_bank`` architecture (the pretrained file has the
    same one when it was trained with these params); it is zero without ``model.latent_bank``.
    """
    model = build_model(params, latent_bank_path=None)
    depth = model.depth_net
    report = {
        "encoder": _counts(depth.encoder),
        "latent_bank": _counts(depth.bank),
        "bank_adapters": _counts(depth.adapters),
        "decoder": _counts(depth.decoder),
        "pose_net": _counts(model.pose_net),
    }
    report["total"] = {key: sum(item[key] for item in report.values()) for key in ("trainable", "frozen")}
    return report


def format_summary(report: dict[str, dict[str, int]]) -> str:
    """A fixed-width table of :func:`model_summary`'s counts."""
    lines = [f"{'component':<16}{'trainable':>14}{'frozen':>14}"]
    for name, counts in report.items():
        lines.append(f"{name:<16}{counts['trainable']:>14,}{counts['frozen']:>14,}")
    return "\n".join(lines)
