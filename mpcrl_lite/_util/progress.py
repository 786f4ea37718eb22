"""Progress bars of the long loops, paid for only where they are shown.

:func:`progress_bar` is ``tqdm`` with two savings at the start of a run: a bar that is not
shown (``disable=True``: ``--quiet``, ``progress=False``) is a stand-in that imports nothing,
and a shown bar outside a Jupyter kernel is the terminal's ``tqdm.std.tqdm`` (what
``tqdm.auto`` chooses there too, without importing ``asyncio`` for its async iteration, which
the loops do not use). In a notebook (IPython imported) it is ``tqdm.auto``'s widget bar.
Measured: ``tqdm.auto`` 0.05 s of import, ``tqdm.std`` 0.035 s, the stand-in nothing.
"""

from __future__ import annotations

import sys
from typing import Any, Self

__all__ = ["progress_bar"]


class _Hidden:
    """A bar that is not shown: the calls of ``tqdm`` the loops make, doing nothing."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def update(self, n: float = 1) -> None:
        return None

    def set_postfix(self, *args: Any, **kwargs: Any) -> None:
        return None

    def set_description(self, *args: Any, **kwargs: Any) -> None:
        return None

    def close(self) -> None:
        return None


def progress_bar(*, disable: bool = False, **kwargs: Any) -> Any:
    """A ``tqdm`` bar with ``kwargs`` (``total``, ``desc``, ``unit``, ``initial`` ...), or a
    stand-in with the same calls (``update``, ``set_postfix``, ``set_description``,
    ``close``, ``with``) that shows nothing when ``disable``."""
    if disable:
        return _Hidden()
    if "IPython" in sys.modules:  # a notebook's kernel, perhaps: tqdm.auto decides
        from tqdm.auto import tqdm
    else:
        from tqdm.std import tqdm
    return tqdm(**kwargs)
