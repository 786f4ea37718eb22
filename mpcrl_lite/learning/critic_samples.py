r"""What the critic learns from in a month, kept for a critic fitted on several months.

With ``LearningConfig.critic_months = K > 1`` the centralized DPG learner fits its compatible
critic (:func:`mpcrl_lite.learning.step.lstd_policy_gradient`) on the samples of the month just
run and of the ``K - 1`` months before it. Each month's samples keep what they were taken
with: the soc, the applied action, the centre of its exploration (the policy's action), the
policy sensitivity of that month's theta, the stage cost, which samples are usable and the
month's buy prices. :class:`CriticSamples` holds one month of them, :meth:`CriticSamples.join`
puts months side by side as one longer month (days after days), and :meth:`~CriticSamples.to_npz`
/ :meth:`~CriticSamples.from_npz` carry the earlier months through a checkpoint
(``critic.npz`` of the run directory), so that a resumed run fits what an uninterrupted one
would.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from .outdir import RunDirError
from .rundir import RECOVER

__all__ = ["CriticSamples"]


@dataclass(frozen=True, eq=False)
class CriticSamples:
    """One month of the critic's samples (``H`` hours, ``D`` days, ``m`` batteries).

    Attributes
    ----------
    soc : (H + 1, D, m)
    a, center : (H, D, m)
        The applied action and the centre of its exploration.
    grad_pi : (H, D, n_theta, m)
        The policy sensitivity of the month's theta.
    cost : (H, D)
        The learner's stage cost.
    use : (H, D) bool
        Samples whose MPC and sensitivity were usable.
    buy : (H, D) or None
        The month's buy prices (read by the price features of the value baseline).
    """

    soc: np.ndarray
    a: np.ndarray
    center: np.ndarray
    grad_pi: np.ndarray
    cost: np.ndarray
    use: np.ndarray
    buy: np.ndarray | None

    @classmethod
    def join(cls, months: Sequence[CriticSamples]) -> CriticSamples:
        """The months as one period whose days are theirs in order (the day axis joined);
        ``buy`` only if every month has it."""
        if not months:
            raise ValueError("no months to join; expected at least one")

        def cat(name: str) -> np.ndarray | None:
            parts = [getattr(m, name) for m in months]
            if any(p is None for p in parts):
                return None
            return np.concatenate(parts, axis=1)

        return cls(**{f.name: cat(f.name) for f in fields(cls)})

    @staticmethod
    def to_npz(months: Sequence[CriticSamples]) -> bytes:
        """The months as the bytes of an uncompressed ``.npz`` (``allow_pickle=False``):
        ``months`` (their number) and ``<i>_<field>`` per month."""
        arrays: dict[str, np.ndarray] = {"months": np.array(len(months))}
        for i, month in enumerate(months):
            for f in fields(CriticSamples):
                value = getattr(month, f.name)
                if value is not None:
                    arrays[f"{i}_{f.name}"] = np.asarray(value)
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        return buffer.getvalue()

    @classmethod
    def from_npz(cls, data: bytes, where: str, n: int, max_months: int) -> list[CriticSamples]:
        """The months of :meth:`to_npz`, checked: at most ``max_months`` months of ``n``
        batteries, every array of the shapes of the class docstring, and all months of the
        same hours, parameters and days. Raises :class:`RunDirError` naming ``where``."""
        def bad(what: str) -> RunDirError:
            return RunDirError(f"{where}: {what}; {RECOVER}")

        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                arrays = {key: npz[key] for key in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise bad(f"not a readable .npz ({err})") from None
        count = arrays.get("months")
        if count is None or count.shape != () or count.dtype.kind not in "iu" \
                or not 0 <= int(count) <= max_months:
            raise bad(f"'months' is {None if count is None else count.tolist()!r}, expected an "
                      f"integer in [0, {max_months}]")
        months = []
        for i in range(int(count)):
            month = cls(**{f.name: arrays.get(f"{i}_{f.name}") for f in fields(cls)})
            months.append(month)
            problem = month._shape_problem(n)
            if problem:
                raise bad(f"month {i}: {problem}")
        if months:
            first = months[0]
            for i, month in enumerate(months[1:], start=1):
                if month.grad_pi.shape != first.grad_pi.shape \
                        or (month.buy is None) != (first.buy is None):
                    raise bad(f"month {i} has grad_pi {month.grad_pi.shape}, month 0 "
                              f"{first.grad_pi.shape}; expected months of the same shapes")
        return months

    def _shape_problem(self, n: int) -> str:
        """What is wrong with this month's arrays for ``n`` batteries ('' if nothing)."""
        for name in ("soc", "a", "center", "grad_pi", "cost", "use"):
            if getattr(self, name) is None:
                return f"{name!r} is missing"
        if self.soc.ndim != 3 or self.soc.shape[2] != n or self.soc.shape[0] < 2:
            return f"soc has shape {self.soc.shape}, expected (hours + 1, days, {n})"
        H, D = self.soc.shape[0] - 1, self.soc.shape[1]
        expected = {"a": (H, D, n), "center": (H, D, n), "cost": (H, D), "use": (H, D)}
        if self.buy is not None:
            expected["buy"] = (H, D)
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                return f"{name} has shape {getattr(self, name).shape}, expected {shape}"
        g = self.grad_pi
        if g.ndim != 4 or g.shape[:2] != (H, D) or g.shape[3] != n:
            return f"grad_pi has shape {g.shape}, expected ({H}, {D}, n_theta, {n})"
        if self.use.dtype != bool:
            return f"use has dtype {self.use.dtype}, expected bool"
        for name in ("soc", "a", "center", "grad_pi", "cost", "buy"):
            value = getattr(self, name)
            if value is not None and value.dtype.kind != "f":
                return f"{name} has dtype {value.dtype}, expected floats"
        return ""
