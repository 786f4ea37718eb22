"""The MPC parameters theta: named parts per agent, and their flat vector.

theta has ten parts, each an array of shape ``(n,)`` (one entry per battery):

======== ================================================================================
name     role in the MPC (paper eqs. 9 and 23a-23c; theta is eq. 24)
======== ================================================================================
alpha    model gain: ``soc+ = soc + theta_alpha (b - s) + theta_delta``
delta    model offset (the mean effect of the production-demand noise)
b        buying price correction: ``(phi_b + theta_b) b``
s        selling price correction: ``-(phi_s + theta_s) s``
phi1     stage cost ``phi1 soc^2 + phi2 soc + phi3``
phi2
phi3     (a constant: it never changes the MPC's solution)
T1       terminal cost ``T1 soc_N^2 + T2 soc_N + T3``
T2
T3       (a constant, like phi3)
======== ================================================================================

The flat vector is ordered part by part, agents inside each part:
``[alpha_1..alpha_n, delta_1..delta_n, b_1.., s_1.., phi1_1.., ..., T3_1..T3_n]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import SystemConfig

__all__ = ["CONSTANT_PARTS", "PARTS", "Theta"]

#: Names of theta's parts in vector order.
PARTS: tuple[str, ...] = ("alpha", "delta", "b", "s", "phi1", "phi2", "phi3", "T1", "T2", "T3")
#: Parts that add a constant to the MPC's cost (zero policy gradient).
CONSTANT_PARTS: tuple[str, ...] = ("phi3", "T3")


@dataclass(frozen=True, eq=False)
class Theta:
    """MPC parameters (paper eq. 24), one array of shape ``(n,)`` per part (see the module
    docstring)."""

    alpha: np.ndarray
    delta: np.ndarray
    b: np.ndarray
    s: np.ndarray
    phi1: np.ndarray
    phi2: np.ndarray
    phi3: np.ndarray
    T1: np.ndarray
    T2: np.ndarray
    T3: np.ndarray

    def __post_init__(self) -> None:
        n = None
        for name in PARTS:
            value = np.array(getattr(self, name), dtype=float).reshape(-1)
            if n is None:
                n = value.size
            if value.size != n or n == 0:
                raise ValueError(
                    f"theta part {name!r} has {value.size} entries; expected {n} (one per agent)"
                )
            if not np.all(np.isfinite(value)):
                raise ValueError(f"theta part {name!r}={value.tolist()}: expected finite numbers")
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def nominal(cls, system: SystemConfig | None = None) -> Theta:
        """theta0: the nominal model (``theta_alpha = alpha``, ``theta_delta = alpha *
        noise_mean``, each battery's own) and no cost corrections."""
        system = system or SystemConfig()
        n = system.n
        zeros = np.zeros(n)
        alpha, mean = np.array(system.battery("alpha")), np.array(system.battery("noise_mean"))
        return cls(
            alpha=alpha,  # each battery's own (one value for all: the same n floats as before)
            delta=alpha * mean,
            **{name: zeros for name in PARTS[2:]},
        )

    @classmethod
    def from_vector(cls, vector: np.ndarray, n: int) -> Theta:
        """Inverse of :meth:`to_vector`; ``vector`` has shape ``(10 n,)``."""
        vector = np.asarray(vector, dtype=float).reshape(-1)
        if vector.size != len(PARTS) * n:
            raise ValueError(
                f"theta vector has {vector.size} entries; expected {len(PARTS) * n} "
                f"({len(PARTS)} parts x n={n})"
            )
        return cls(**{name: vector[i * n : (i + 1) * n] for i, name in enumerate(PARTS)})

    @classmethod
    def from_dict(cls, data: dict[str, list[float]]) -> Theta:
        """Inverse of :meth:`to_dict`."""
        missing = set(PARTS) - set(data)
        if missing:
            raise ValueError(f"theta dict lacks parts {sorted(missing)}")
        return cls(**{name: np.asarray(data[name], dtype=float) for name in PARTS})

    # -- views ----------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of agents."""
        return self.alpha.size

    @property
    def size(self) -> int:
        """Length of the flat vector (10 n)."""
        return len(PARTS) * self.n

    def to_vector(self) -> np.ndarray:
        """Flat vector of shape ``(10 n,)`` in the order of :data:`PARTS`."""
        return np.concatenate([getattr(self, name) for name in PARTS])

    def to_dict(self) -> dict[str, list[float]]:
        """``{part: [value per agent]}``, JSON-friendly."""
        return {name: getattr(self, name).tolist() for name in PARTS}

    def replace(self, **parts: np.ndarray) -> Theta:
        """A copy with some parts replaced."""
        data = {name: getattr(self, name) for name in PARTS}
        unknown = set(parts) - set(PARTS)
        if unknown:
            raise ValueError(f"unknown theta part(s) {sorted(unknown)}; expected some of {PARTS}")
        data.update(parts)
        return Theta(**data)

    def is_convex(self) -> bool:
        """True when the MPC is a convex QP for this theta (``phi1, T1 >= 0``)."""
        return bool(np.all(self.phi1 >= 0) and np.all(self.T1 >= 0))

    @staticmethod
    def names(n: int) -> list[str]:
        """Names of the vector's entries, e.g. ``'delta[2]'`` (agents counted from 1)."""
        return [f"{name}[{i + 1}]" for name in PARTS for i in range(n)]

    @staticmethod
    def mask(n: int, parts: tuple[str, ...] | list[str]) -> np.ndarray:
        """Boolean mask of shape ``(10 n,)`` selecting the given parts."""
        unknown = set(parts) - set(PARTS)
        if unknown:
            raise ValueError(f"unknown theta part(s) {sorted(unknown)}; expected some of {PARTS}")
        return np.repeat([name in parts for name in PARTS], n)

    @staticmethod
    def index(n: int, part: str) -> slice:
        """Slice of the flat vector holding ``part``."""
        if part not in PARTS:
            raise ValueError(f"unknown theta part {part!r}; expected one of {PARTS}")
        i = PARTS.index(part)
        return slice(i * n, (i + 1) * n)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Theta) and np.array_equal(self.to_vector(), other.to_vector())

    def __repr__(self) -> str:
        body = ", ".join(f"{name}={np.round(getattr(self, name), 6).tolist()}" for name in PARTS)
        return f"Theta({body})"
