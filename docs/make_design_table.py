"""Write the module table of docs/design.md from the modules' own docstrings.

Every ``.py`` file of ``src/napari_dvc_correct`` gets a row: its path in the package and the first
sentence of its docstring (Sphinx roles such as ``:func:`x``` shown as ```x```). The table sits
between the two marker lines of docs/design.md; the rest of the page is left as it is. Run it
after adding, renaming or redescribing a module::

    python docs/make_design_table.py          # rewrite the table in docs/design.md
    python docs/make_design_table.py --check  # exit 1 if the table is not the code's

The modules are read with :mod:`ast`, never imported, so the script runs without the package's
dependencies.
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]
PACKAGE = REPOSITORY / "src" / "napari_dvc_correct"
DESIGN = REPOSITORY / "docs" / "design.md"
BEGIN = (
    "<!-- module table: written by docs/make_design_table.py from the docstrings; do not edit -->"
)
END = "<!-- end of the module table -->"

_ROLE = re.compile(r":(?:mod|func|class|meth|attr|data|obj):`~?([^`]+)`")
_SENTENCE_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z(`*])")


def modules(package: Path = PACKAGE) -> list[Path]:
    """Every module of the package, sorted by path (a folder's ``__init__.py`` first)."""
    return sorted(package.rglob("*.py"), key=lambda p: p.relative_to(package).parts)


def summary(path: Path) -> str:
    """The first sentence of the module's docstring, as Markdown on one line."""
    docstring = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"), str(path)))
    if not docstring:
        raise ValueError(f"{path}: no module docstring: say in one sentence what it holds")
    paragraph = " ".join(docstring.split("\n\n")[0].split())
    sentence = _SENTENCE_END.split(paragraph, maxsplit=1)[0]
    sentence = _ROLE.sub(lambda m: f"`{m.group(1)}`", sentence).replace("``", "`")
    return sentence.replace("|", "\\|")


def table(package: Path = PACKAGE) -> str:
    """The Markdown table: one row per module, path in the package and what it does."""
    rows = ["| module | what it does (its docstring's first sentence) |", "|---|---|"]
    for path in modules(package):
        rows.append(f"| `{path.relative_to(package).as_posix()}` | {summary(path)} |")
    return "\n".join(rows)


def with_table(page: str, new_table: str) -> str:
    """``page`` with the text between the markers replaced by ``new_table``."""
    if page.count(BEGIN) != 1 or page.count(END) != 1 or page.index(BEGIN) > page.index(END):
        raise ValueError(f"docs/design.md needs the two marker lines, once each:\n{BEGIN}\n{END}")
    head, rest = page.split(BEGIN)
    _, tail = rest.split(END)
    return f"{head}{BEGIN}\n{new_table}\n{END}{tail}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only say whether it is current")
    args = parser.parse_args(argv)
    page = DESIGN.read_text(encoding="utf-8")
    new_page = with_table(page, table())
    if args.check:
        if new_page != page:
            print(
                "docs/design.md's module table is out of date: run python docs/make_design_table.py"
            )
            return 1
        return 0
    if new_page != page:
        temporary = DESIGN.with_name(DESIGN.name + ".tmp")
        temporary.write_text(new_page, encoding="utf-8")
        temporary.replace(DESIGN)  # atomic: the page is never half written
    return 0


if __name__ == "__main__":
    sys.exit(main())
