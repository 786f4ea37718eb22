"""Opening the notebooks elsewhere: Colab and Binder links, and the install cell.

Every notebook starts with a launch line (Colab and Binder badges) and, as its first code cell,
:func:`install_cell_source`: on Colab or a JupyterHub without the package it installs
``mpcrl_lite`` from the repository with pip; wherever the package is importable (``make
setup``, Binder, ``pip install .``) it does nothing. No cell downloads anything else: the data
and the notebooks ship inside the package.

The text of those cells is generated here, from :data:`REPOSITORY` and :data:`BRANCH`, by
``python tools/update_launch_cells.py`` (a fork changes the two constants and runs it;
``tests/publish/test_site.py`` checks that the notebooks match).
"""

from __future__ import annotations

import copy

from .._util.references import PAPER, citation_markdown

__all__ = [
    "BRANCH",
    "INSTALL_TAG",
    "LAUNCH_MARKER",
    "NOTEBOOK_FOLDER",
    "PAPER_MARKER",
    "REPOSITORY",
    "STUDENT_FOLDER",
    "apply_launch_cells",
    "binder_folder_url",
    "binder_repo_url",
    "binder_url",
    "colab_url",
    "install_cell_source",
    "install_requirement",
    "launch_badges",
    "paper_line",
    "student_launch_line",
]

#: ``owner/name`` of the public GitHub repository that Colab and Binder open.
REPOSITORY = "mpcrl-lite/mpcrl_lite"
#: Branch (or tag) whose notebooks and package the links open.
BRANCH = "main"
#: Folder of the notebooks inside the repository.
NOTEBOOK_FOLDER = "notebooks"
#: Folder of the student version (solutions removed): written by ``make student`` and by
#: Binder's ``binder/postBuild``, not kept in the repository.
STUDENT_FOLDER = "student"
#: First words of a notebook's launch line (how the tools find it in the first cell).
LAUNCH_MARKER = "[![Open in Colab]"
#: First words of the citation paragraph that ends a notebook's first cell.
PAPER_MARKER = "**Paper.**"
#: Tag of the install cell (the first code cell of every notebook).
INSTALL_TAG = "install"

_COLAB_BADGE = "https://colab.research.google.com/assets/colab-badge.svg"
_BINDER_BADGE = "https://mybinder.org/badge_logo.svg"

# Extras a notebook's kernel needs besides the package (installed by the first cell).
_EXTRAS = {"07": ("classroom", "sweep")}
_DEFAULT_EXTRAS = ("classroom",)


def _stem(notebook: str) -> str:
    name = notebook.rsplit("/", 1)[-1]
    return name.removesuffix(".ipynb")


def colab_url(notebook: str, repository: str = REPOSITORY, branch: str = BRANCH) -> str:
    """Open ``notebook`` (stem or file name) from the repository in Google Colab."""
    return (f"https://colab.research.google.com/github/{repository}/blob/{branch}/"
            f"{NOTEBOOK_FOLDER}/{_stem(notebook)}.ipynb")


def binder_repo_url(repository: str = REPOSITORY, branch: str = BRANCH) -> str:
    """Binder's JupyterLab on the whole repository (notebooks and ``student/`` alike)."""
    return f"https://mybinder.org/v2/gh/{repository}/{branch}"


def binder_url(notebook: str, repository: str = REPOSITORY, branch: str = BRANCH,
               folder: str = NOTEBOOK_FOLDER) -> str:
    """Open ``notebook`` in JupyterLab on Binder (built from ``binder/``), from ``folder``
    (the teacher's ``notebooks/`` or the :data:`STUDENT_FOLDER`)."""
    return (f"{binder_repo_url(repository, branch)}?urlpath=lab/tree/{folder}/"
            f"{_stem(notebook)}.ipynb")


def binder_folder_url(folder: str = STUDENT_FOLDER, repository: str = REPOSITORY,
                      branch: str = BRANCH) -> str:
    """Binder's JupyterLab opened at ``folder`` (default the student version)."""
    return f"{binder_repo_url(repository, branch)}?urlpath=lab/tree/{folder}"


def student_launch_line(notebook: str, repository: str = REPOSITORY,
                        branch: str = BRANCH) -> str:
    """The launch line of the student copy of ``notebook``: a Binder badge that opens the
    student copy (Binder writes ``student/`` when it builds), and how to open it on Colab,
    which opens only files kept in the repository: upload this one."""
    return (f"[![Launch on Binder]({_BINDER_BADGE})]"
            f"({binder_url(notebook, repository, branch, STUDENT_FOLDER)}) "
            "(the student version, without solutions). On Colab: *File → Upload notebook* "
            "with this file; its first cell installs the package.")


def launch_badges(notebook: str, repository: str = REPOSITORY, branch: str = BRANCH) -> str:
    """The markdown launch line of ``notebook``: a Colab and a Binder badge."""
    return (f"{LAUNCH_MARKER}({_COLAB_BADGE})]({colab_url(notebook, repository, branch)}) "
            f"[![Launch on Binder]({_BINDER_BADGE})]({binder_url(notebook, repository, branch)})")


def install_requirement(notebook: str, repository: str = REPOSITORY,
                        branch: str = BRANCH) -> str:
    """The pip requirement that the first cell of ``notebook`` installs when needed."""
    extras = _EXTRAS.get(_stem(notebook)[:2], _DEFAULT_EXTRAS)
    return f"mpcrl_lite[{','.join(extras)}] @ git+https://github.com/{repository}@{branch}"


def install_cell_source(notebook: str, repository: str = REPOSITORY,
                        branch: str = BRANCH) -> str:
    """The first code cell of ``notebook``: install the package only where it is missing."""
    requirement = install_requirement(notebook, repository, branch)
    return (
        "# Colab or a JupyterHub without mpcrl_lite: install it (about a minute, once per\n"
        "# session). Where the package is importable already (make setup, Binder, pip install .)\n"
        "# this cell does nothing.\n"
        "import importlib\n"
        "import importlib.util\n"
        "import subprocess\n"
        "import sys\n"
        "\n"
        f'requirement = "{requirement}"\n'
        'if importlib.util.find_spec("mpcrl_lite") is None:\n'
        '    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", requirement],\n'
        "                   check=True)\n"
        "    importlib.invalidate_caches()"
    )


def paper_line() -> str:
    """The citation paragraph that ends every notebook's first cell."""
    return (f"{PAPER_MARKER} {citation_markdown(PAPER)} Equation numbers \"paper eq. N\" in "
            "these notebooks refer to it.")


def apply_launch_cells(nb, stem: str, repository: str = REPOSITORY, branch: str = BRANCH):
    """A copy of notebook ``nb`` with its launch line, citation and install cell up to date.

    The first cell (the title) gets :func:`launch_badges` right after the title line and
    :func:`paper_line` as its last paragraph; the first code cell is the install cell
    (tagged :data:`INSTALL_TAG`, id ``install-NN``), inserted before the parameters cell if
    missing. Applying it twice changes nothing.
    """
    import nbformat

    out = copy.deepcopy(nb)
    title = out.cells[0]
    if title.cell_type != "markdown" or not title.source.startswith("# "):
        raise ValueError(f"{stem}: the first cell must be the markdown title cell")
    paragraphs = [p for p in title.source.split("\n\n")
                  if not p.startswith(LAUNCH_MARKER) and not p.startswith(PAPER_MARKER)]
    head, _, rest = paragraphs[0].partition("\n")
    paragraphs = [head, launch_badges(stem, repository, branch)] + (
        [rest] if rest.strip() else []) + paragraphs[1:] + [paper_line()]
    title.source = "\n\n".join(paragraphs)
    source = install_cell_source(stem, repository, branch)
    code = [c for c in out.cells if c.cell_type == "code"]
    if code and INSTALL_TAG in code[0].get("metadata", {}).get("tags", []):
        code[0].source = source
    else:
        cell = nbformat.v4.new_code_cell(source)
        cell.id = f"install-{stem[:2]}"
        cell.metadata["tags"] = [INSTALL_TAG]
        out.cells.insert(out.cells.index(code[0]) if code else 1, cell)
    return out
