"""Trainable and frozen parameter counts per component of the model that the params describe, beside the
paper's released code."""

from __future__ import annotations

from torch import nn

from endoflow.config import Params
from endoflow.models.endoflow_model import build_model

COMPONENTS = ("encoder", "latent_bank", "bank_adapters", "decoder", "pose_net")

# Parameters (millions) of the paper's released code (Xu et al., CVPR 2025), per component, counted by hand
# from its model definitions (issue 10); its latent bank is frozen, the rest trained. Components it has no
# separate figure for (our bank adapters, the total) are left out rather than guessed.
RELEASED_CODE_MILLIONS: dict[str, float] = {
    "encoder": 5.2,
    "latent_bank": 75.8,
    "decoder": 2.3,
    "pose_net": 12.5,
}


def _counts(module: nn.Module | None) -> dict[str, int]:
    params = list(module.parameters()) if module is not None else []
    return {
        "trainable": sum(p.numel() for p in params if p.requires_grad),
        "frozen": sum(p.numel() for p in params if not p.requires_grad),
    }


def model_summary(params: Params) -> dict[str, dict[str, int | float | None]]:
    """``{component: {"trainable": n, "frozen": n, "released_code_millions": m}}`` for each of
    :data:`COMPONENTS`, plus ``total``.

    The latent bank is counted with the ``params.latent_bank`` architecture (the pretrained file has the
    same one when it was trained with these params); it is zero without ``model.latent_bank``.
    ``released_code_millions`` is the released code's figure from :data:`RELEASED_CODE_MILLIONS` (``None``
    where it has none), so every reader of the summary sees where our architecture departs from it.
    """
    model = build_model(params, latent_bank_path=None)
    depth = model.depth_net
    counts = {
        "encoder": _counts(depth.encoder),
        "latent_bank": _counts(depth.bank),
        "bank_adapters": _counts(depth.adapters),
        "decoder": _counts(depth.decoder),
        "pose_net": _counts(model.pose_net),
    }
    counts["total"] = {key: sum(item[key] for item in counts.values()) for key in ("trainable", "frozen")}
    return {
        name: {**item, "released_code_millions": RELEASED_CODE_MILLIONS.get(name)} for name, item in counts.items()
    }


def format_summary(report: dict[str, dict[str, int | float | None]]) -> str:
    """A fixed-width table of :func:`model_summary`'s counts: ours exactly, then ours and the released code's
    in millions side by side."""
    header = f"{'component':<16}{'trainable':>14}{'frozen':>14}{'ours (M)':>11}{'released code (M)':>20}"
    lines = [header]
    for name, item in report.items():
        ours = (item["trainable"] + item["frozen"]) / 1e6
        released = item["released_code_millions"]
        released_text = "-" if released is None else f"{released:.1f}"
        lines.append(
            f"{name:<16}{item['trainable']:>14,}{item['frozen']:>14,}{ours:>11.1f}{released_text:>20}"
        )
    lines.append("released code: counted by hand from the paper's released model definitions (issue 10)")
    return "\n".join(lines)
