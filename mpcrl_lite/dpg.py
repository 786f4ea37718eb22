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
that keeps the MPC a convex QP with a unique solution. The update rules themselves (one class
each) live in :mod:`mpcrl_lite.update_rules`.

Why Adam with per-part scales by default: theta's parts have unrelated units (a model gain of
order 1/12, price corrections in NOK/MWh, soc cost weights in NOK), so one step size cannot
serve them all. On the paper's system the first gradient has norm ~1e8, almost all of it in
theta_alpha: the paper's step 5e-8 throws theta_alpha from 1/12 to ~3.5 while the cost weights
do not move. Adam normalises each entry by its own gradient history and moves it by at most
about ``step_size`` times its typical magnitude (:data:`DEFAULT_SCALE`), whatever the units.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from .config import (
    ConfigWarning,
    LearningConfig,
    SystemConfig,
    check_instance,
    check_int,
    check_real,
)
from .theta import CONSTANT_PARTS, PARTS, Theta
from .update_rules import (
    ADAM_BETAS,
    ADAM_EPS,
    ADAM_STEP_SIZE,
    STATE_KEYS,
    UpdateRule,
    make_update_rule,
)

__all__ = [
    "ADAM_BETAS",
    "ADAM_EPS",
    "ADAM_STEP_SIZE",
    "DEFAULT_SCALE",
    "DPGUpdater",
    "learnable_mask",
    "part_scales",
    "policy_gradient",
]


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
    system_alpha = check_real("system_alpha", system_alpha, 0.0, low_open=True)
    price_scale = check_real("price_scale", price_scale, 0.0, low_open=True)
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
    n = check_int("n", n, 1)
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
        Adam only: decay rates of the first and second moments.
    eps : float, default :data:`ADAM_EPS`
        Adam only: denominator guard.
    scale : dict, optional
        Adam only: typical magnitude of each part, ``{part: float}``; parts not given keep
        the default of :func:`part_scales` (``system_alpha`` for ``alpha`` and ``delta``,
        :data:`DEFAULT_SCALE` for the others).
    price_scale : float, default 1
        Multiplier of the default scales of the cost parts (prices not in NOK/MWh).

    Attributes
    ----------
    rule : UpdateRule
        The update rule named by ``config.optimizer`` (:data:`~mpcrl_lite.update_rules.
        UPDATE_RULES`), which turns each masked gradient into the step's direction.
    scale : array, shape ``(10 n,)``
        Typical magnitude of each entry (used by Adam and by ``grad_norm_scaled``).

    Notes
    -----
    **Direction** (:mod:`mpcrl_lite.update_rules`). With ``'sgd'``
    (:class:`~mpcrl_lite.update_rules.GradientDescent`) the direction is the gradient itself,
    the paper's rule
    :math:`\theta \leftarrow \theta - \alpha\nabla_\theta J` (``step_size`` = the paper's
    :math:`\alpha`, 5e-8). With ``'adam'`` (:class:`~mpcrl_lite.update_rules.Adam`) it is

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
        self.config = check_instance("config", config, LearningConfig)
        self.mask = learnable_mask(n, config.learn_constants)
        self.n = int(n)
        self.system_alpha = check_real("system_alpha", system_alpha, 0.0, low_open=True)
        self.scale = self._scale_vector(scale or {}, price_scale)
        self.rule: UpdateRule = make_update_rule(
            config.optimizer, len(PARTS) * self.n, scale=self.scale, betas=betas, eps=eps
        )
        if config.keep_well_posed and config.alpha_min >= system_alpha:
            warnings.warn(
                f"alpha_min={config.alpha_min:g} >= system alpha={system_alpha:g}: the "
                "projection will move theta_alpha away from the true model",
                ConfigWarning,
                stacklevel=2,
            )
        doubt = self.rule.step_size_warning(config.step_size)
        if doubt:
            warnings.warn(doubt, ConfigWarning, stacklevel=2)
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
            parts[name] = check_real(f"scale[{name!r}]", value, 0.0, low_open=True)
        return np.repeat([parts[name] for name in PARTS], self.n)

    # -- state ----------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the optimizer state (step count and the rule's state, e.g. Adam's
        moments)."""
        self.step_count = 0
        self.rule.reset()
        self.last_info: dict[str, Any] = {}

    def state_dict(self) -> dict[str, Any]:
        """JSON-friendly state (lists, floats, ints, str): enough to resume exactly.

        Keys ``optimizer``, ``n``, ``step_count``, ``m`` and ``v`` for every rule (``m`` and
        ``v`` are Adam's moments, zeros for a rule that keeps none), so checkpoints of every
        rule, old and new, share one layout.
        """
        arrays = self.rule.state_arrays()
        zeros = np.zeros(len(PARTS) * self.n)
        return {
            "optimizer": self.config.optimizer,
            "n": self.n,
            "step_count": int(self.step_count),
            **{key: arrays.get(key, zeros).tolist() for key in STATE_KEYS},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` (same optimizer and ``n`` required)."""
        expected = {"optimizer", "n", "step_count", *STATE_KEYS}
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
        for key in STATE_KEYS:
            value = np.asarray(state[key], dtype=float)
            if value.shape != (size,) or not np.all(np.isfinite(value)):
                raise ValueError(
                    f"state {key!r} has shape {value.shape}; expected ({size},) finite numbers"
                )
            moments[key] = value
        self.step_count = count
        self.rule.load_state_arrays(moments)

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
        direction = self.rule.direction(g, self.step_count)
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
