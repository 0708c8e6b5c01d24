"""The repository explains itself: tests shaped like the package, docs drawn from the code, and
a source that cites only what the repository holds.

Every module ``src/napari_dvc_correct/<folder>/<name>.py`` has its test file
``tests/<folder>/test_<name>.py`` (a leading underscore dropped; a package's ``__init__.py`` that
holds code: ``tests/<folder>/test_<package>.py``), and that file imports the module by name.

Docstrings and comments may point to the paper (its sections, equations and figures) and to the
files under ``docs/``; they must not point to documents a reader of the repository does not have
(a specification kept elsewhere, an issue tracker's numbers). Each rule is a scan of the source
with a pattern that is first shown to catch what it is meant to catch.
"""

from __future__ import annotations

import ast
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


def test_the_test_files_the_documentation_cites_exist():
    cited = {
        (page.name, name)
        for page in (REPOSITORY / "docs").glob("*.md")
        for name in re.findall(r"\btests/[\w/]+\.py\b", page.read_text(encoding="utf-8"))
    }
    assert cited, "the scan found no test file cited in docs/"
    missing = sorted(f"docs/{page} cites {name}" for page, name in cited
                     if not (REPOSITORY / name).is_file())  # fmt: skip
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


# --- tests shaped like the package ----------------------------------------------------------------
#: Modules that cannot have an in-process test file of their own, and where they are tested.
_SIMULATOR = (
    "numba.cuda code runs only on a GPU or in numba's CUDA simulator, which must be switched on "
    "before numba is imported: tests/engine/cuda/test_icgn.py runs it in a subprocess "
    "(tests/engine/cuda/_simulate.py) against the CPU engine"
)
CANNOT = {
    "__init__.py": "the package's marker: a docstring, nothing to run",
    "engine/cuda/icgn.py": _SIMULATOR,
    "engine/cuda/sampling.py": _SIMULATOR,
    "engine/cuda/device_algebra.py": _SIMULATOR + " (device functions: callable only in a kernel)",
}

#: Modules still tested only through other modules' tests, or whose test file does not import
#: them by name yet: a list that can only shrink (a test below fails once one of them is done).
NOT_YET: dict[str, str] = {
    "commands/_grid_options.py": "reached through the correlate and correct commands' tests; "
    "the command-line argument code is being reworked around the option records",
}


def expected_test_file(module: Path) -> Path:
    """Where the tests of ``module`` (a path under the package) live."""
    relative = module.relative_to(ROOT)
    if module.name == "__init__.py":
        return REPOSITORY / "tests" / relative.parent / f"test_{relative.parent.name}.py"
    return REPOSITORY / "tests" / relative.parent / f"test_{module.stem.lstrip('_')}.py"


def _only_re_exports(module: Path) -> bool:
    """A package ``__init__.py`` of a docstring, imports and ``__all__`` only: nothing to test."""
    if module.name != "__init__.py":
        return False
    for node in ast.parse(module.read_text()).body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            continue  # the docstring
        if isinstance(node, ast.Assign) and [getattr(t, "id", "") for t in node.targets] == [
            "__all__"
        ]:
            continue
        return False
    return True


def _module_name(module: Path) -> str:
    parts = list(module.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports_by_name(test_file: Path, name: str) -> bool:
    """Whether ``test_file`` imports module ``name`` (``import a.b``, ``from a.b import x`` or
    ``from a import b``), anywhere in the file."""
    parent, _, leaf = name.rpartition(".")
    for node in ast.walk(ast.parse(test_file.read_text(), str(test_file))):
        if isinstance(node, ast.Import) and any(a.name == name for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and node.module == name:
            return True
        if (
            isinstance(node, ast.ImportFrom)
            and node.module == parent
            and any(a.name == leaf for a in node.names)
        ):
            return True
    return False


def _modules_to_test() -> list[Path]:
    return [
        m
        for m in _sources()
        if m.relative_to(ROOT).as_posix() not in CANNOT and not _only_re_exports(m)
    ]


def test_the_rule_maps_modules_to_their_test_files():
    engine = ROOT / "engine"
    assert expected_test_file(engine / "correlation" / "match_judgement.py") == (
        REPOSITORY / "tests/engine/correlation/test_match_judgement.py"
    )
    assert expected_test_file(engine / "_numba_setup.py") == (
        REPOSITORY / "tests/engine/test_numba_setup.py"
    )
    assert expected_test_file(ROOT / "report" / "__init__.py") == (
        REPOSITORY / "tests/report/test_report.py"
    )
    assert _only_re_exports(engine / "__init__.py")
    assert not _only_re_exports(ROOT / "report" / "__init__.py")
    here = Path(__file__)
    assert _imports_by_name(here, "pytest") and not _imports_by_name(here, "numpy")


def test_every_module_has_its_test_file_which_imports_it():
    missing, unimported = [], []
    for module in _modules_to_test():
        relative = module.relative_to(ROOT).as_posix()
        if relative in NOT_YET:
            continue
        test_file = expected_test_file(module)
        names = [_module_name(module)]
        if relative.startswith("commands/"):  # a subcommand is tested by running it
            names.append(f"{PACKAGE}.cli")
        if not test_file.is_file():
            missing.append(f"{relative} -> {test_file.relative_to(REPOSITORY)}")
        elif not any(_imports_by_name(test_file, name) for name in names):
            unimported.append(f"{test_file.relative_to(REPOSITORY)} never imports {relative}")
    assert not missing, "modules without their test file:\n" + "\n".join(missing)
    assert not unimported, "\n".join(unimported)


def test_the_lists_of_exceptions_are_current():
    modules = {m.relative_to(ROOT).as_posix(): m for m in _sources()}
    assert set(CANNOT) <= set(modules), set(CANNOT) - set(modules)
    assert set(NOT_YET) <= set(modules), set(NOT_YET) - set(modules)
    done = [
        name
        for name in NOT_YET
        if expected_test_file(modules[name]).is_file()
        and _imports_by_name(expected_test_file(modules[name]), _module_name(modules[name]))
    ]
    assert not done, f"these have their test file now: take them off NOT_YET: {done}"
