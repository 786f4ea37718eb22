r"""The actor: the deterministic policy gradient and the update of theta.

With the compatible critic of :mod:`mpcrl_lite.lstd`,
:math:`\nabla_a Q_w(s, a) = \nabla_\theta\pi_\theta(s)^\top w`, the deterministic policy
gradient of the paper (Section III) is

.. math::

    \nabla_\theta J(\pi_\theta)
    = \mathbb E\big[\nabla_\theta\pi_\theta(s)\,
      \nabla_a A_{\pi_\theta}(s, a)|_{a=\pi_\theta(s)}\big]
    \approx \frac1S \sum_{\text{samples}} \nabla_\theta\pi_\theta(s)\,
      \nabla_\theta\pi_\theta(s)^\top w ,

and the paper's update is the plain gradient step
:math:`\theta \leftarrow \theta - \alpha \nabla_\theta J` (the cost is minimised).

:class:`DPGUpdater` applies that step (``optimizer='sgd'``) or an Adam step (the default), only
to the learnable parts of theta, with optional clipping of the step and an optional projection
that keeps the MPC a convex QP with a unique solution.

Why Adam with per-part scales by default: theta's parts have unrelated units (a model gain of
order 1/12, price corrections in NOK/MWh, soc cost weights in NOK), so one step size cannot
serve them all. On the paper's system the first gradient has norm ~1e8, almost all of it in
theta_alpha: the paper's step 5e-8 throws theta_alpha from 1/12 to ~3.5 while the cost weights
do not move. Adam normalises each entry by its own gradient history and moves it by at most
about ``step_size`` times its typical magnitude (:data:`DEFAULT_SCALE`), whatever the units.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from .config import ConfigWarning, LearningConfig, SystemConfig
from .theta import CONSTANT_PARTS, PARTS, Theta

__all__ = [
    "policy_gradient",
    "learnable_mask",
    "DPGUpdater",
    "ADAM_BETAS",
    "ADAM_EPS",
    "ADAM_STEP_SIZE",
    "DEFAULT_SCALE",
    "part_scales",
]

#: Adam's moment decay rates (beta1, beta2), the usual defaults.
ADAM_BETAS: tuple[float, float] = (0.9, 0.999)
#: Adam's denominator guard.
ADAM_EPS: float = 1e-8
#: A sensible ``LearningConfig.step_size`` for ``optimizer='adam'`` (the default): each
#: learnable entry moves by at most about 2 % of its scale per update (see
#: :class:`DPGUpdater`). Measured on the paper's system: 0.05 lets the first, noisiest
#: months push single batteries far in a wrong direction (one battery then keeps selling
#: into the penalised zone for tens of months, in 2 of 3 seeds); with 0.02 all 6 seeds tried
#: learned within 100 months.
ADAM_STEP_SIZE: float = 2e-2

#: Typical magnitude of each part of theta for Adam, for prices in NOK/MWh (multiplied by
#: ``SystemConfig.price_scale`` in :meth:`DPGUpdater.from_configs`). ``None`` means "the true
#: battery factor ``SystemConfig.alpha``" (theta_alpha and theta_delta are soc per MWh and soc
#: per hour). Price corrections: 10 NOK/MWh, a fifth of the mean price. soc cost weights:
#: 100 NOK per unit of soc (or soc^2), about a seventh of the value of a full battery
#: (12 MWh x ~56 NOK/MWh).
DEFAULT_SCALE: dict[str, float | None] = {
    "alpha": None,
    "delta": None,
    "b": 10.0,
    "s": 10.0,
    "phi1": 100.0,
    "phi2": 100.0,
    "phi3": 100.0,
    "T1": 100.0,
    "T2": 100.0,
    "T3": 100.0,
}


def part_scales(system_alpha: float, price_scale: float = 1.0) -> dict[str, float]:
    """:data:`DEFAULT_SCALE` made concrete: ``alpha``/``delta`` get ``system_alpha``, the cost
    parts are multiplied by ``price_scale`` (the ``SystemConfig.price_scale`` of the prices).
    """
    system_alpha = float(system_alpha)
    price_scale = float(price_scale)
    if not (math.isfinite(system_alpha) and system_alpha > 0):
        raise ValueError(f"system_alpha={system_alpha!r}: expected a finite value > 0")
    if not (math.isfinite(price_scale) and price_scale > 0):
        raise ValueError(f"price_scale={price_scale!r}: expected a finite value > 0")
    return {
        name: system_alpha if value is None else value * price_scale
        for name, value in DEFAULT_SCALE.items()
    }


def policy_gradient(grad_pi: np.ndarray, w: np.ndarray) -> np.ndarray:
    r"""Sample estimate of :math:`\nabla_\theta J = \mathbb E[\nabla_\theta\pi\,
    \nabla_\theta\pi^\top w]`.

    Parameters
    ----------
    grad_pi : array, shape ``(..., n_theta, n)``
        Policy sensitivities of the samples; the leading dimensions (e.g. ``(hours, days)``)
        are averaged over. A single ``(n_theta, n)`` matrix is one sample.
    w : array, shape ``(n_theta,)``
        Weights of the compatible critic (``LSTDResult.w``).

    Returns
    -------
    grad : array, shape ``(n_theta,)``
    """
    grad_pi = np.asarray(grad_pi, dtype=float)
    w = np.asarray(w, dtype=float)
    if grad_pi.ndim < 2:
        raise ValueError(f"grad_pi has shape {grad_pi.shape}; expected (..., n_theta, n)")
    n_theta, n = grad_pi.shape[-2:]
    if w.shape != (n_theta,):
        raise ValueError(
            f"w has shape {w.shape}; expected ({n_theta},) to match grad_pi {grad_pi.shape}"
        )
    samples = grad_pi.reshape(-1, n_theta, n)
    if samples.shape[0] == 0:
        raise ValueError(f"grad_pi has shape {grad_pi.shape}: no samples")
    action_gradient = np.einsum("sti,t->si", samples, w)  # grad_a Q_w at a = pi, (S, n)
    return np.einsum("sti,si->t", samples, action_gradient) / samples.shape[0]


def learnable_mask(n: int, learn_constants: bool = False) -> np.ndarray:
    """Which entries of the flat theta vector are updated.

    Parameters
    ----------
    n : int
        Number of agents.
    learn_constants : bool
        Also learn ``phi3`` and ``T3`` (:data:`~mpcrl_lite.theta.CONSTANT_PARTS`), whose
        policy gradient is always zero.

    Returns
    -------
    mask : bool array, shape ``(10 n,)``
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n={n!r}: expected an integer >= 1")
    if learn_constants:
        return np.ones(len(PARTS) * n, dtype=bool)
    return ~Theta.mask(n, CONSTANT_PARTS)


class DPGUpdater:
    r"""Gradient steps on theta: ``theta <- project(theta - clip(step_size * direction))``.

    Parameters
    ----------
    config : LearningConfig
        Uses ``step_size``, ``optimizer``, ``learn_constants``, ``grad_clip``,
        ``keep_well_posed`` and ``alpha_min``.
    n : int
        Number of agents (theta has ``10 n`` entries).
    system_alpha : float
        The true battery factor ``SystemConfig.alpha``: the natural scale of the model parts
        ``alpha`` and ``delta`` for Adam, and a sanity check of ``alpha_min``.
    betas : (float, float), default :data:`ADAM_BETAS`
        Adam's decay rates of the first and second moments.
    eps : float, default :data:`ADAM_EPS`
        Adam's denominator guard.
    scale : dict, optional
        Adam only: typical magnitude of each part, ``{part: float}``; parts not given keep
        the default of :func:`part_scales` (``system_alpha`` for ``alpha`` and ``delta``,
        :data:`DEFAULT_SCALE` for the others).
    price_scale : float, default 1
        Multiplier of the default scales of the cost parts (prices not in NOK/MWh).

    Notes
    -----
    **Direction.** With ``'sgd'`` the direction is the gradient itself, the paper's rule
    :math:`\theta \leftarrow \theta - \alpha\nabla_\theta J` (``step_size`` = the paper's
    :math:`\alpha`, 5e-8). With ``'adam'`` it is

    .. math::

        m_t = \beta_1 m_{t-1} + (1-\beta_1) g_t, \quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2) g_t^2, \quad
        d_t = \sigma \odot \frac{m_t / (1-\beta_1^t)}{\sqrt{v_t / (1-\beta_2^t)} + \epsilon},

    with :math:`\sigma` the per-entry ``scale``. Adam's direction is normalised (each entry is
    at most about 1 in units of its scale), so its ``step_size`` is a *relative move per
    update*, not a multiplier of the gradient: the paper's 5e-8 would leave theta
    practically unchanged; :data:`ADAM_STEP_SIZE` = 1e-2 is a sensible start.

    **Mask.** Entries outside :func:`learnable_mask` have their gradient zeroed before
    anything else, so they never change (and Adam's moments for them stay zero).

    **Clipping.** If ``grad_clip`` is set and :math:`\|\text{step}\|_2 >` ``grad_clip``, the
    step is rescaled to norm ``grad_clip`` (direction kept). Adam's moments still see the
    raw gradient.

    **Projection.** If ``keep_well_posed``: ``alpha >= alpha_min``, ``phi1 >= 0``,
    ``T1 >= 0`` entrywise, which keeps the MPC a convex QP with a unique solution.

    After each :meth:`step`, :attr:`last_info` records ``step`` (count), ``grad_norm`` (of
    the masked gradient), ``grad_norm_scaled`` (of the masked gradient times ``scale``: the
    gradient with respect to theta measured in its parts' typical magnitudes, which does not
    depend on their units), ``raw_step_norm``, ``step_norm`` (after clipping), ``clipped``,
    ``projected`` (names like ``'phi1[2]'`` of the entries moved by the projection) and
    ``projection_norm``.
    """

    def __init__(
        self,
        config: LearningConfig,
        n: int,
        system_alpha: float,
        *,
        betas: tuple[float, float] = ADAM_BETAS,
        eps: float = ADAM_EPS,
        scale: dict[str, float] | None = None,
        price_scale: float = 1.0,
    ) -> None:
        if not isinstance(config, LearningConfig):
            raise ValueError(f"config={config!r}: expected a LearningConfig")
        self.config = config
        self.mask = learnable_mask(n, config.learn_constants)
        self.n = int(n)
        system_alpha = float(system_alpha)
        if not (math.isfinite(system_alpha) and system_alpha > 0):
            raise ValueError(f"system_alpha={system_alpha!r}: expected a finite value > 0")
        self.system_alpha = system_alpha
        if len(betas) != 2 or not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"betas={betas!r}: expected two values in [0, 1)")
        self.betas = (float(betas[0]), float(betas[1]))
        if not (math.isfinite(eps) and eps > 0):
            raise ValueError(f"eps={eps!r}: expected a finite value > 0")
        self.eps = float(eps)
        self.scale = self._scale_vector(scale or {}, price_scale)
        if config.keep_well_posed and config.alpha_min >= system_alpha:
            warnings.warn(
                f"alpha_min={config.alpha_min:g} >= system alpha={system_alpha:g}: the "
                "projection will move theta_alpha away from the true model",
                ConfigWarning,
                stacklevel=2,
            )
        if config.optimizer == "adam" and config.step_size < 1e-4:
            warnings.warn(
                f"step_size={config.step_size:g} with optimizer='adam': Adam's step size is a "
                f"relative move per update, so theta will hardly change; try "
                f"{ADAM_STEP_SIZE:g}",
                ConfigWarning,
                stacklevel=2,
            )
        self._lower = np.full(len(PARTS) * self.n, -np.inf)
        self._lower[Theta.index(self.n, "alpha")] = config.alpha_min
        self._lower[Theta.index(self.n, "phi1")] = 0.0
        self._lower[Theta.index(self.n, "T1")] = 0.0
        self._names = Theta.names(self.n)
        self.reset()

    @classmethod
    def from_configs(cls, learning: LearningConfig, system: SystemConfig, **kwargs: Any):
        """Build from the two configs (``n``, ``alpha`` and ``price_scale`` taken from
        ``system``)."""
        kwargs.setdefault("price_scale", system.price_scale if system.price_scale > 0 else 1.0)
        return cls(learning, system.n, system.alpha, **kwargs)

    def _scale_vector(self, scale: dict[str, float], price_scale: float) -> np.ndarray:
        unknown = set(scale) - set(PARTS)
        if unknown:
            raise ValueError(
                f"scale has unknown part(s) {sorted(unknown)}; expected some of {PARTS}"
            )
        parts = part_scales(self.system_alpha, price_scale)
        for name, value in scale.items():
            value = float(value)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"scale[{name!r}]={value!r}: expected a finite value > 0")
            parts[name] = value
        return np.repeat([parts[name] for name in PARTS], self.n)

    # -- state ----------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the optimizer state (step count and Adam's moments)."""
        size = len(PARTS) * self.n
        self.step_count = 0
        self._m = np.zeros(size)
        self._v = np.zeros(size)
        self.last_info: dict[str, Any] = {}

    def state_dict(self) -> dict[str, Any]:
        """JSON-friendly state (lists, floats, ints, str): enough to resume exactly."""
        return {
            "optimizer": self.config.optimizer,
            "n": self.n,
            "step_count": int(self.step_count),
            "m": self._m.tolist(),
            "v": self._v.tolist(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` (same optimizer and ``n`` required)."""
        expected = {"optimizer", "n", "step_count", "m", "v"}
        if set(state) != expected:
            raise ValueError(f"state has keys {sorted(state)}; expected {sorted(expected)}")
        if state["optimizer"] != self.config.optimizer:
            raise ValueError(
                f"state optimizer={state['optimizer']!r}; expected {self.config.optimizer!r}"
            )
        if state["n"] != self.n:
            raise ValueError(f"state n={state['n']!r}; expected {self.n}")
        count = state["step_count"]
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"state step_count={count!r}: expected an integer >= 0")
        size = len(PARTS) * self.n
        moments = {}
        for key in ("m", "v"):
            value = np.asarray(state[key], dtype=float)
            if value.shape != (size,) or not np.all(np.isfinite(value)):
                raise ValueError(
                    f"state {key!r} has shape {value.shape}; expected ({size},) finite numbers"
                )
            moments[key] = value
        self.step_count = count
        self._m, self._v = moments["m"], moments["v"]

    # -- update ---------------------------------------------------------------------------
    def step(self, theta: Theta, grad: np.ndarray) -> Theta:
        r"""One update: ``theta - step_size * direction(grad)``, masked, clipped, projected.

        Parameters
        ----------
        theta : Theta
            Current parameters (``theta.n`` must equal ``n``).
        grad : array, shape ``(10 n,)``
            :math:`\nabla_\theta J` in the flat order of :meth:`Theta.to_vector`.

        Returns
        -------
        Theta
            The updated parameters; :attr:`last_info` describes the step.
        """
        if not isinstance(theta, Theta) or theta.n != self.n:
            raise ValueError(f"theta={theta!r}: expected a Theta with n={self.n}")
        grad = np.asarray(grad, dtype=float)
        if grad.shape != self.mask.shape:
            raise ValueError(f"grad has shape {grad.shape}; expected {self.mask.shape} (10 n)")
        if not np.all(np.isfinite(grad)):
            raise ValueError("grad contains non-finite values (nan or inf)")
        g = np.where(self.mask, grad, 0.0)
        self.step_count += 1
        if self.config.optimizer == "sgd":
            direction = g
        else:
            b1, b2 = self.betas
            t = self.step_count
            self._m = b1 * self._m + (1.0 - b1) * g
            self._v = b2 * self._v + (1.0 - b2) * g**2
            m_hat = self._m / (1.0 - b1**t)
            v_hat = self._v / (1.0 - b2**t)
            direction = self.scale * m_hat / (np.sqrt(v_hat) + self.eps)
        step = self.config.step_size * direction
        raw_norm = float(np.linalg.norm(step))
        clip = self.config.grad_clip
        clipped = clip is not None and raw_norm > clip
        if clipped:
            step = step * (clip / raw_norm)
        moved = theta.to_vector() - step
        new = np.maximum(moved, self._lower) if self.config.keep_well_posed else moved
        hit = new != moved
        self.last_info = {
            "step": self.step_count,
            "grad_norm": float(np.linalg.norm(g)),
            "grad_norm_scaled": float(np.linalg.norm(self.scale * g)),
            "raw_step_norm": raw_norm,
            "step_norm": float(np.linalg.norm(step)),
            "clipped": bool(clipped),
            "projected": [name for name, h in zip(self._names, hit) if h],
            "projection_norm": float(np.linalg.norm(new - moved)),
        }
        return Theta.from_vector(new, self.n)

    def __repr__(self) -> str:
        c = self.config
        return (
            f"DPGUpdater(optimizer={c.optimizer!r}, step_size={c.step_size:g}, n={self.n}, "
            f"learnable={int(self.mask.sum())}/{self.mask.size}, step_count={self.step_count})"
        )
