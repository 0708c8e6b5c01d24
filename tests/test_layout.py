"""The repository explains itself: its source cites only what the repository holds.

Docstrings and comments may point to the paper (its sections, equations and figures) and to the
files under ``docs/``; they must not point to documents a reader of the repository does not have
(a specification kept elsewhere, an issue tracker's numbers). Each rule is a scan of the source
with a pattern that is first shown to catch what it is meant to catch.
"""

from __future__ import annotations

import re
from pathlib import Path

PACKAGE = "napari_dvc_correct"
REPOSITORY = Path(__file__).resolve().parents[1]
ROOT = REPOSITORY / "src" / PACKAGE

#: A specification section ("SPEC §3", "see SPEC") or an issue number ("issue 13", "issues 10/14",
#: "(issue 27 item 5)"): documents outside the repository.
OUTSIDE = re.compile(r"\bSPEC\b|\bissues?\s*#?\d+|\(issue\b")
#: A file of the documentation cited by path.
DOCS = re.compile(r"\bdocs/([\w./-]+\.md)\b")


def _sources() -> list[Path]:
    return sorted(ROOT.rglob("*.py"))


def test_the_patterns_catch_what_they_are_meant_to():
    for text in ("(SPEC §3, paper Fig. 3)", "Conventions (see SPEC)", "one interface (issue 13).",
                 "the fault case of issue 10", "(issue 27 item 5)", "issues 10/14"):  # fmt: skip
        assert OUTSIDE.search(text), text
    for text in ("paper Fig. 3", "see docs/method.md", "an issue of memory", "SPECTRUM 3"):
        assert not OUTSIDE.search(text), text
    assert DOCS.findall("measured in docs/method.md; see ``docs/evaluation.md``") == [
        "method.md",
        "evaluation.md",
    ]


def test_no_reference_to_documents_outside_the_repository():
    found = [
        f"{path.relative_to(REPOSITORY)}:{number}: {line.strip()}"
        for path in _sources()
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not found, "say the thing itself, or cite docs/ or the paper:\n" + "\n".join(found)


def test_the_documentation_the_source_cites_exists():
    cited = {(path, name) for path in _sources() for name in DOCS.findall(path.read_text())}
    assert cited, "the scan found no citation of docs/ at all"
    missing = sorted(
        f"{path.relative_to(REPOSITORY)} cites docs/{name}"
        for path, name in cited
        if not (REPOSITORY / "docs" / name).is_file()
    )
    assert not missing, missing
