"""The suite's housekeeping: a module's fixture folders go when it passes and stay when it fails, so that a run of
the suite does not fill the disk and a failure can still be looked at."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

CONFTEST = Path(__file__).with_name("conftest.py")
PROJECT = CONFTEST.parent.parent

INNER_MODULE = """
import pytest

made = []

@pytest.fixture(scope="module")
def folder(module_tmp):
    made.append(module_tmp("data"))
    (made[-1] / "file").write_text("x")
    return made[-1]

def test_uses_the_folder(folder):
    assert (folder / "file").exists()

def test_outcome(folder):
    assert {outcome}
"""


@pytest.mark.parametrize("passes", [True, False])
def test_a_module_folder_goes_when_the_module_passes_and_stays_when_it_fails(
        pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch, passes: bool) -> None:
    monkeypatch.setenv("PYTHONPATH", str(PROJECT))  # the conftest imports from tests/
    pytester.makeconftest(CONFTEST.read_text())
    pytester.makepyfile(test_inner=INNER_MODULE.format(outcome=passes))
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", f"--basetemp={pytester.path / 'temp'}")
    result.assert_outcomes(passed=2 if passes else 1, failed=0 if passes else 1)
    kept = sorted(path.name for path in (pytester.path / "temp").iterdir() if not path.is_symlink())
    assert kept == ([] if passes else ["data0"])
