"""Where the files shipped with the package live: the price data and the notebooks.

The repository keeps them in top-level folders (``data/``, ``notebooks/``), the one copy that is
edited. A wheel carries the same files inside the package (``mpcrl_lite/data``,
``mpcrl_lite/notebooks``; ``pyproject.toml`` maps the folders at build time), so an installed
package finds them through :mod:`importlib.resources`, whatever the working directory, while a
source checkout or an editable install reads the top-level folders next to the package.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["SHIPPED_FOLDERS", "candidate_folders", "package_folder"]

#: Folders of the repository that the wheel carries inside the package, under the same names.
SHIPPED_FOLDERS = ("data", "notebooks")


def candidate_folders(name: str) -> list[Path]:
    """Where ``name`` may live, in the order searched: inside the installed package, then the
    checkout's top-level folder next to the package."""
    if name not in SHIPPED_FOLDERS:
        raise ValueError(f"name={name!r}: expected one of {list(SHIPPED_FOLDERS)}")
    inside = resources.files("mpcrl_lite") / name
    checkout = Path(__file__).resolve().parents[2] / name
    # A package imported from the file system gives a real path; from a zip archive it does
    # not, and then only the checkout's folder can be read as files.
    found = [Path(str(inside))] if isinstance(inside, Path) else []
    return found + [checkout]


def package_folder(name: str) -> Path:
    """The folder ``name`` (``'data'`` or ``'notebooks'``) shipped with this copy of the package.

    Returns the first existing of :func:`candidate_folders`, or the first candidate when none
    exists (reading from it then fails with a message that names the folder).
    """
    candidates = candidate_folders(name)
    for folder in candidates:
        if folder.is_dir():
            return folder
    return candidates[0]
