"""The front door stays a front door: README.md is short and names every stage DVC runs, and no relative link in
README.md or docs/*.md points at a file or heading that is not there (a moved section breaks the links to it)."""

from __future__ import annotations

import re
from pathlib import Path

from tests.project_clone import PROJECT

README = PROJECT / "README.md"
README_MAX_LINES = 150
PAGES = [README, *sorted((PROJECT / "docs").glob("*.md"))]

FENCED_BLOCK = re.compile(r"^[ \t]*(```|~~~).*?^[ \t]*\1", re.MULTILINE | re.DOTALL)
CODE_SPAN = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.MULTILINE)


def prose(markdown: str) -> str:
    """``markdown`` without code blocks and code spans, where brackets and parentheses are code, not links."""
    return CODE_SPAN.sub("", FENCED_BLOCK.sub("", markdown))


def heading_anchors(markdown: str) -> set[str]:
    """The anchors GitHub gives the headings: lower case, punctuation but ``-`` and ``_`` dropped, spaces to
    ``-``, a repeated anchor numbered ``-1``, ``-2``, ..."""
    anchors: set[str] = set()
    for heading in HEADING.findall(FENCED_BLOCK.sub("", markdown)):
        base = re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")
        anchor, count = base, 0
        while anchor in anchors:
            count += 1
            anchor = f"{base}-{count}"
        anchors.add(anchor)
    return anchors


def broken_links(page: Path) -> list[str]:
    """Each relative link of ``page`` whose file does not exist, or whose ``#anchor`` is no heading of a Markdown
    target, as ``'<target>: <why>'``."""
    broken = []
    for target in LINK.findall(prose(page.read_text(encoding="utf-8"))):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        path = (page.parent / path_part).resolve() if path_part else page
        if not path.exists():
            broken.append(f"{target}: no file {path}")
        elif anchor and path.suffix == ".md" and anchor not in heading_anchors(path.read_text(encoding="utf-8")):
            broken.append(f"{target}: no heading with anchor #{anchor} in {path.name}")
    return broken


def stages_in_readme_table(markdown: str) -> set[str]:
    """Stage names in the first column of README's tables: `` `train` `` names ``train``, and
    `` `evaluate@simcol_12`, `@simcol_3` `` names ``evaluate@simcol_12`` and ``evaluate@simcol_3``."""
    named: set[str] = set()
    for line in markdown.splitlines():
        if not line.startswith("| `"):
            continue
        base = None
        for span in re.findall(r"`([^`]+)`", line.split("|")[1]):
            if span.startswith("@") and base:
                named.add(base + span)
            else:
                named.add(span)
                base = span.split("@")[0]
    return named


def dvc_stage_names() -> list[str]:
    """Every stage DVC runs, as ``dvc stage list`` names them (each ``foreach`` item as ``stage@item``)."""
    from dvc.repo import Repo

    with Repo(str(PROJECT)) as repo:
        return [stage.addressing for stage in repo.index.stages]


def test_every_relative_link_in_readme_and_docs_resolves():
    broken = {page.name: found for page in PAGES if (found := broken_links(page))}
    assert not broken, broken


def test_the_link_check_finds_a_missing_file_and_a_missing_heading(tmp_path: Path):
    (tmp_path / "other.md").write_text("# A heading (`with/code.py`)\n\n## Twice\n\n## Twice\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md#a-heading-withcodepy) [second](other.md#twice-1) [web](https://example.org/x)\n"
                    "`[code](nowhere.md)`\n\n```\n[block](nowhere.md)\n```\n"
                    "- item\n\n  ```\n  [indented block](nowhere.md)\n  ```\n"
                    "[gone](missing.md) [no heading](other.md#nothing) ![picture](img/none.png)\n")
    assert [entry.split(":")[0] for entry in broken_links(page)] == ["missing.md", "other.md#nothing",
                                                                       "img/none.png"]


def test_readme_is_at_most_150_lines():
    lines = len(README.read_text(encoding="utf-8").splitlines())
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines (at most {README_MAX_LINES}): move detail to docs/"


def test_readme_stage_table_names_every_stage_of_dvc_yaml():
    stages = dvc_stage_names()
    assert stages, "DVC lists no stage in dvc.yaml"
    missing = [name for name in stages if name not in stages_in_readme_table(README.read_text(encoding="utf-8"))]
    assert not missing, f"README.md's stage table lacks {missing}"
