"""`endoflow.io.write_json` writes JSON that any reader takes: a NaN or an infinity (which Python's json would write
as `NaN`, refused by other readers) is refused naming the file and the key, and the old file is kept."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from endoflow.io import write_json


def test_nan_or_infinity_is_refused_naming_the_file_and_key_and_the_old_file_stays(tmp_path: Path) -> None:
    path = tmp_path / "depth.json"
    write_json(path, {"unit_cm": 0.001, "preview_range_cm": [1.0, 5.0]})
    with pytest.raises(ValueError, match=r"depth\.json: not written: preview_range_cm\[1\] is nan, a number JSON "
                                         r"cannot hold"):
        write_json(path, {"unit_cm": 0.001, "preview_range_cm": [1.0, np.float32("nan")]})
    with pytest.raises(ValueError, match=r"not written: ratios\.b is -inf"):
        write_json(path, {"ratios": {"a": 1, "b": -np.inf}})
    assert json.loads(path.read_text()) == {"unit_cm": 0.001, "preview_range_cm": [1.0, 5.0]}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["depth.json"]
