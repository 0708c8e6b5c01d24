"""The repository explains itself: its source cites only what the repository holds.

Docstrings and comments may point to the paper (its sections, equations and figures) and to the
files under ``docs/``; they must not point to documents a reader of the repository does not have
(a specification kept elsewhere, an issue tracker's numbers). Each rule is a scan of the source
with a pattern that is first shown to catch what it is meant to catch.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

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


# --- docs/design.md's module table is the code's -------------------------------------------------
def _design_table_script():
    spec = importlib.util.spec_from_file_location(
        "make_design_table", REPOSITORY / "docs" / "make_design_table.py"
    )
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def _listed(page: str, script) -> set[str]:
    between = page.split(script.BEGIN)[1].split(script.END)[0]
    return set(re.findall(r"^\| `([^`]+\.py)` \|", between, flags=re.MULTILINE))


def test_the_design_table_script_reads_docstrings(tmp_path):
    script = _design_table_script()
    package = tmp_path / "package"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text('"""The package."""\n')
    (package / "sub" / "thing.py").write_text(
        '"""Does :func:`.work` with ``a | b``, in two\nlines. Then more.\n\nDetails."""\n'
    )
    assert [p.relative_to(package).as_posix() for p in script.modules(package)] == [
        "__init__.py",
        "sub/thing.py",
    ]
    assert (
        script.summary(package / "sub" / "thing.py") == "Does `.work` with `a \\| b`, in two lines."
    )
    table = script.table(package)
    assert table.splitlines()[2:] == [
        "| `__init__.py` | The package. |",
        "| `sub/thing.py` | Does `.work` with `a \\| b`, in two lines. |",
    ]
    page = f"# Title\n{script.BEGIN}\nold rows\n{script.END}\nafter\n"
    assert script.with_table(page, "NEW") == f"# Title\n{script.BEGIN}\nNEW\n{script.END}\nafter\n"
    assert _listed(script.with_table(page, table), script) == {"__init__.py", "sub/thing.py"}
    with pytest.raises(ValueError, match="marker"):
        script.with_table("# no markers\n", table)
    (package / "bare.py").write_text("x = 1\n")
    with pytest.raises(ValueError, match="no module docstring"):
        script.summary(package / "bare.py")


def test_every_module_is_in_the_design_table():
    script = _design_table_script()
    page = (REPOSITORY / "docs" / "design.md").read_text(encoding="utf-8")
    listed = _listed(page, script)
    modules = {p.relative_to(ROOT).as_posix() for p in _sources()}
    assert modules - listed == set(), "run python docs/make_design_table.py: modules missing"
    assert listed - modules == set(), "run python docs/make_design_table.py: modules gone"
    assert script.with_table(page, script.table()) == page, (
        "docs/design.md's module table is not the docstrings': run python docs/make_design_table.py"
    )
