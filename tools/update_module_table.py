"""Write the README's module table (section "Layout and data flow") from the package itself:
one row per module or subpackage, its docstring's first paragraph as the description.

    python tools/update_module_table.py          # rewrite the table in README.md
    python tools/update_module_table.py --check  # exit 1 if the table is out of date

``tests/package/test_architecture.py`` checks that the table lists every module.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "mpcrl_lite"
README = ROOT / "README.md"
START = "| module | what it holds |\n|---|---|\n"
#: the order of the rows: the data flow, lowest first
ORDER = ["mpcrl_lite", "config", "theta", "_util", "system", "mpc", "sim", "learning",
         "decentralized", "bounds", "figures", "classroom", "publish", "studies", "cli"]


def modules() -> list[str]:
    """Dotted names below ``mpcrl_lite`` (``'mpcrl_lite'`` for the package itself)."""
    names = []
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
        if parts == ["__main__"]:
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names.append(".".join(parts) or "mpcrl_lite")
    return sorted(names, key=lambda m: (ORDER.index(m.split(".")[0]), m))


def _summary(name: str) -> str:
    base = PACKAGE.joinpath(*([] if name == "mpcrl_lite" else name.split(".")))
    path = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    first = " ".join(doc.split("\n\n")[0].split()).replace("|", "\\|")
    return first if len(first) <= 150 else first[:first.rfind(" ", 0, 147)] + " ..."


def table() -> str:
    return START + "".join(f"| `{m}` | {_summary(m)} |\n" for m in modules())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check, write nothing")
    args = parser.parse_args(argv)
    text = README.read_text()
    start = text.index(START)
    end = text.index("\n\n", start) + 1
    new = text[:start] + table() + text[end:]
    if args.check:
        return 0 if new == text else 1
    README.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
