"""``params.yaml`` written from the schema: every key with its default (or a preset's value), what it means and
its unit as a comment, so the file DVC reads is complete and documents itself.

``endoflow params --preset presets/paper.yaml --out params.yaml`` writes the paper preset's full set; with no
preset it writes the defaults, which is what the committed params.yaml holds.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any, Optional

import yaml
from pydantic.fields import FieldInfo

from endoflow.config import Params, Section, load_params
from endoflow.io import write_text

HEADER = """\
# endoflow parameters: the schema's defaults (endoflow/config.py){source}, written by `endoflow params`.
# Every key is listed (DVC tracks params by key); a key left out of a file endoflow reads takes its default.
# Ablations: `dvc exp run -S model.latent_bank=false`. Other complete sets: `endoflow params --preset FILE`.
"""
WIDTH = 116


def params_yaml(params: Params, source: Optional[str] = None) -> str:
    """The full YAML text of ``params``, each key under a comment saying what it is; ``source`` names the preset."""
    lines = HEADER.format(source=f" with {source}" if source else "").splitlines()
    lines += _section_lines(params, indent=0, documented=True)
    return "\n".join(lines) + "\n"


def preset_yaml(preset: Optional[str | Path] = None) -> str:
    """The full params text of the defaults, or of ``preset``'s differences over them."""
    params = load_params(preset) if preset is not None else Params()
    return params_yaml(params, source=str(preset) if preset is not None else None)


def write_params_file(out: str | Path, preset: Optional[str | Path] = None) -> Params:
    """Write the full params (the defaults, or ``preset``'s differences over them) to ``out``, atomically."""
    write_text(out, preset_yaml(preset))
    return load_params(out)


def _section_lines(section: Section, indent: int, documented: bool) -> list[str]:
    lines: list[str] = []
    pad = " " * indent
    for name, info in type(section).model_fields.items():
        value = getattr(section, name)
        if documented:
            lines += _comment(info, pad)
        if isinstance(value, Section):
            lines.append(f"{pad}{name}:")
            lines += _section_lines(value, indent + 2, documented)
        elif isinstance(value, dict) and value and all(isinstance(v, Section) for v in value.values()):
            lines.append(f"{pad}{name}:")
            for entry, item in value.items():
                lines.append(f"{pad}  {_scalar(entry)}:")
                lines += _section_lines(item, indent + 4, documented=False)
        else:
            lines.append(f"{pad}{name}: {_scalar(value)}")
    return lines


def _comment(info: FieldInfo, pad: str) -> list[str]:
    unit = (info.json_schema_extra or {}).get("unit")
    text = info.description or ""
    if unit:
        text = f"{text} [{unit}]" if text else f"[{unit}]"
    if not text:
        return []
    return textwrap.wrap(text, width=WIDTH - len(pad), initial_indent=f"{pad}# ", subsequent_indent=f"{pad}#   ")


def _scalar(value: Any) -> str:
    """``value`` as one line of YAML (flow style for lists and mappings)."""
    text = yaml.safe_dump(value, default_flow_style=True, width=10**6, sort_keys=False).strip()
    return text.removesuffix("\n...").strip()
