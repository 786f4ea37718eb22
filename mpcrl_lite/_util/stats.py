"""Means with Student-t confidence intervals: the one summary of K noise draws or seeds."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["MeanCI", "mean_ci", "t_quantile"]


def t_quantile(p: float, df: int) -> float:
    """The ``p`` quantile of Student's t with ``df`` degrees of freedom.

    ``scipy.special.stdtrit`` is what ``scipy.stats.t.ppf`` evaluates (the same numbers to
    the last bit); importing it here, on first use, keeps ``scipy.stats`` (about a second)
    out of every import of the package.
    """
    from scipy.special import stdtrit

    return float(stdtrit(df, p))


@dataclass(frozen=True)
class MeanCI:
    """Mean of K values, their sample standard deviation and the confidence interval of the
    mean; ``std``, ``ci_low`` and ``ci_high`` are NaN for a single value."""

    mean: float
    std: float
    ci_low: float
    ci_high: float
    draws: int

    def as_dict(self) -> dict[str, Any]:
        """``{"mean", "std", "ci_low", "ci_high", "draws"}`` for JSON: NaN becomes None."""
        def plain(x: float) -> float | None:
            return None if math.isnan(x) else x

        return {"mean": self.mean, "std": plain(self.std), "ci_low": plain(self.ci_low),
                "ci_high": plain(self.ci_high), "draws": self.draws}


def mean_ci(values: Any, level: float = 0.95) -> MeanCI:
    r"""Mean of ``values`` and its Student-t confidence interval.

    ``mean -+ t_{(1+level)/2, K-1} * sd / sqrt(K)`` for ``K`` values (``sd`` with ``K - 1``
    degrees of freedom).

    Parameters
    ----------
    values : array_like, any shape (flattened to K values)
    level : float in (0, 1)

    Returns
    -------
    MeanCI
        With NaN spread and interval for K = 1.
    """
    if not (isinstance(level, float) and 0.0 < level < 1.0):
        raise ValueError(f"level={level!r}: expected a float in (0, 1)")
    x = np.asarray(values, dtype=float).reshape(-1)
    if x.size == 0:
        raise ValueError("values: expected at least one value")
    mean = float(x.mean())
    if x.size < 2:
        return MeanCI(mean, math.nan, math.nan, math.nan, 1)
    std = float(x.std(ddof=1))
    half = t_quantile(0.5 + level / 2, x.size - 1) * std / math.sqrt(x.size)
    return MeanCI(mean, std, mean - half, mean + half, int(x.size))
