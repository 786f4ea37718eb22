r"""The actor: the deterministic policy gradient and the update of theta.

With the compatible critic of :mod:`mpcrl_lite.learning.lstd`,
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

:class:`DPGUpdater` applies that step (``optimizer='sgd'``), an Adam step (the default) or a
natural-gradient step (``'natural'``), only to the learnable parts of theta -- by default one
value per part shared by the identical batteries (``tie_agents``) -- with an optional step
schedule (warm-up, decay), clipping, a trust region on the change of the policy, averaging of
the iterates, and a projection that keeps the MPC a convex QP with a unique solution. The
update rules themselves (one class each) live in :mod:`mpcrl_lite.learning.update_rules`; the metric
:math:`F = \mathbb E[\nabla_\theta\pi\nabla_\theta\pi^\top]` the natural gradient and the
trust region need is given with :meth:`DPGUpdater.observe` (:func:`policy_metric`).

Why Adam with per-part scales by default: theta's parts have unrelated units (a model gain of
order 1/12, price corrections in NOK/MWh, soc cost weights in NOK), so one step size cannot
serve them all. On the paper's system the first gradient has norm ~1e8, almost all of it in
theta_alpha: the paper's step 5e-8 throws theta_alpha from 1/12 to ~3.5 while the cost weights
do not move. Adam normalises each entry by its own gradient history and moves it by at most
about ``step_size`` times its typical magnitude (:data:`DEFAULT_SCALE`), whatever the units.
The natural gradient removes the hand-set scales altogether (with the compatible critic it is
the critic's ``w``), but measured on 5 seeds it learned more slowly and failed on some
(``benchmarks/README.md``): a battery whose action sits near a bound has a tiny
:math:`\nabla_\theta\pi`, so a small first-order change of its action asks for a large change
of theta. Averaging the iterates (``average_months``) made the run oscillate with Adam's own
momentum, and a decaying step slowed the learning more than it calmed the end; both stay
options, off by default.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from .._util.validate import check_instance, check_int, check_real
from ..config import ConfigWarning, LearningConfig, SystemConfig
from ..theta import CONSTANT_PARTS, PARTS, Theta
from .update_rules import (
    ADAM_BETAS,
    ADAM_EPS,
    STATE_KEYS,
    UpdateRule,
    make_update_rule,
)

__all__ = ["DEFAULT_SCALE", "REFERENCE_PRICE", "DPGUpdater", "learnable_mask", "part_scales",
           "policy_gradient", "policy_metric", "price_level", "scales_follow_prices"]


#: Typical magnitude of each part of theta for Adam, for prices in NOK/MWh at the shipped
#: month's level (multiplied by ``SystemConfig.price_scale`` in :meth:`DPGUpdater.from_configs`,
#: or by the learning month's :func:`price_level` where ``LearningConfig.scale_to_prices``
#: says so, e.g. for a month read from a file). ``None`` means "the true
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


#: The price level :data:`DEFAULT_SCALE` is set for: the shipped month's mean buying price
#: (NOK/MWh; :func:`mpcrl_lite.system.prices.load_default_profile`, NO3 November 2020).
REFERENCE_PRICE = 56.34688545236111


def price_level(buy: Any) -> float:
    """The price level of a month for Adam's scales of the cost parts
    (``LearningConfig.scale_to_prices``): its mean buying price over :data:`REFERENCE_PRICE`,
    exactly 1 for the shipped month. ``buy`` is the month's buying prices (any shape) or a
    :class:`~mpcrl_lite.system.prices.Prices`."""
    buy = np.asarray(getattr(buy, "buy", buy), dtype=float)
    if buy.size == 0 or not np.all(np.isfinite(buy)):
        raise ValueError(f"price_level of {buy.size} buying prices: expected finite prices")
    mean = float(buy.mean())
    level = mean / REFERENCE_PRICE
    if not level > 0.0:
        raise ValueError(
            f"the month's mean buying price is {mean!r}: Adam's scales cannot "
            "follow a price level that is not positive; expected scale_to_prices=False "
            "(--no-scale-to-prices) for these prices")
    return level


def scales_follow_prices(learning: LearningConfig, prices: Any) -> bool:
    """``learning.scale_to_prices`` resolved for the learning month ``prices``: as given,
    or (``None``) True exactly when the prices were read from a file (their ``origin`` names
    one)."""
    if learning.scale_to_prices is not None:
        return learning.scale_to_prices
    return bool((getattr(prices, "origin", None) or {}).get("file"))


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
    r"""Sample estimate (paper eq. 13 with the compatible critic) of :math:`\nabla_\theta J = \mathbb E[\nabla_\theta\pi\,
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


def policy_metric(grad_pi: np.ndarray) -> np.ndarray:
    r"""Sample estimate of the metric :math:`F = \mathbb E[\nabla_\theta\pi\,
    \nabla_\theta\pi^\top]` of the policy's actions.

    A change :math:`\Delta\theta` moves the actions by :math:`\nabla_\theta\pi^\top
    \Delta\theta` to first order, so :math:`\Delta\theta^\top F \Delta\theta` is the mean
    square change of the action over the samples. With the compatible critic the policy
    gradient is :math:`F w` (:func:`policy_gradient`), and :math:`F` plays the part of the
    Fisher information in the natural gradient :math:`F^{-1}\nabla_\theta J = w`
    (:class:`mpcrl_lite.learning.update_rules.NaturalGradient`).

    Parameters
    ----------
    grad_pi : array, shape ``(..., n_theta, n)``
        Policy sensitivities of the samples; the leading dimensions are averaged over.

    Returns
    -------
    F : array, shape ``(n_theta, n_theta)``
        Symmetric positive semi-definite.
    """
    grad_pi = np.asarray(grad_pi, dtype=float)
    if grad_pi.ndim < 2:
        raise ValueError(f"grad_pi has shape {grad_pi.shape}; expected (..., n_theta, n)")
    n_theta, n = grad_pi.shape[-2:]
    samples = grad_pi.reshape(-1, n_theta, n)
    if samples.shape[0] == 0:
        raise ValueError(f"grad_pi has shape {grad_pi.shape}: no samples")
    flat = samples.transpose(1, 0, 2).reshape(n_theta, -1)  # (n_theta, S n)
    return flat @ flat.T / samples.shape[0]


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
        ``keep_well_posed``, ``alpha_min``, ``tie_agents``, ``natural_damping``,
        ``step_warmup``, ``step_decay``,
        ``max_policy_change`` and ``average_months``.
    n : int
        Number of agents (theta has ``10 n`` entries).
    system_alpha : float or sequence of float
        The true battery factor ``SystemConfig.alpha`` (one for all agents, or one per
        agent): the natural scale of the model parts ``alpha`` and ``delta`` for Adam (each
        agent's own), and a sanity check of ``alpha_min``.
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
        The update rule named by ``config.optimizer`` (:data:`~mpcrl_lite.learning.update_rules.
        UPDATE_RULES`), which turns each masked gradient into the step's direction.
    scale : array, shape ``(10 n,)``
        Typical magnitude of each entry (used by Adam and by ``grad_norm_scaled``).

    Notes
    -----
    **Direction** (:mod:`mpcrl_lite.learning.update_rules`). With ``'sgd'``
    (:class:`~mpcrl_lite.learning.update_rules.GradientDescent`) the direction is the gradient itself,
    the paper's rule
    :math:`\theta \leftarrow \theta - \alpha\nabla_\theta J` (``step_size`` = the paper's
    :math:`\alpha`, 5e-8). With ``'adam'`` (:class:`~mpcrl_lite.learning.update_rules.Adam`) it is

    .. math::

        m_t = \beta_1 m_{t-1} + (1-\beta_1) g_t, \quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2) g_t^2, \quad
        d_t = \sigma \odot \frac{m_t / (1-\beta_1^t)}{\sqrt{v_t / (1-\beta_2^t)} + \epsilon},

    with :math:`\sigma` the per-entry ``scale``. Adam's direction is normalised (each entry is
    at most about 1 in units of its scale), so its ``step_size`` is a *relative move per
    update*, not a multiplier of the gradient: the paper's 5e-8 would leave theta
    practically unchanged; :data:`ADAM_STEP_SIZE` = 1e-2 is a sensible start.

    With ``'natural'`` (:class:`~mpcrl_lite.learning.update_rules.NaturalGradient`) it is the
    natural gradient in the metric of the policy's actions, normalised so that
    ``step_size`` is the RMS change of the action per update in MW; the metric
    :math:`F = \mathbb E[\nabla_\theta\pi\nabla_\theta\pi^\top]` of the month is given
    with :meth:`observe` before each :meth:`step`.

    **Mask.** Entries outside :func:`learnable_mask` have their gradient (and their rows and
    columns of the metric) zeroed before anything else, so they never change (and Adam's
    moments for them stay zero).

    **Tying.** With ``tie_agents`` the gradient (and the metric) are projected onto the
    parameters shared by the agents of a group (``groups``; by default one group: all of
    them): each part's gradient is replaced by its mean over the agents of the group, so
    every agent's entry of a part moves alike within a group. Only identical batteries are
    tied (:meth:`from_configs` takes the groups of
    :meth:`~mpcrl_lite.config.SystemConfig.battery_groups`): on a mixed site, e.g. one large
    and two equal small batteries, the large one learns its own parameters and the two small
    ones share theirs; batteries that all differ are not tied at all.

    **Step size.** ``step_size`` at update ``t``, times ``min(1, t / step_warmup)`` when
    ``step_warmup > 0`` and divided by ``1 + (t - 1) / step_decay`` when ``step_decay > 0``.

    **Clipping.** If ``grad_clip`` is set and :math:`\|\text{step}\|_2 >` ``grad_clip``, the
    step is rescaled to norm ``grad_clip`` (direction kept). Adam's moments still see the
    raw gradient.

    **Trust region.** If ``max_policy_change`` is set, the step is rescaled (direction kept)
    so that :math:`\sqrt{\text{step}^\top F\,\text{step}}`, the RMS change of the action
    to first order, is at most ``max_policy_change`` MW (needs :meth:`observe`).

    **Projection.** If ``keep_well_posed``: ``alpha >= alpha_min``, ``phi1 >= 0``,
    ``T1 >= 0`` entrywise, which keeps the MPC a convex QP with a unique solution.

    **Averaging.** If ``average_months = M > 0``, the steps move a raw iterate
    :math:`\rho` (kept in the state) and the parameters returned, the ones in use, are its
    running average :math:`\theta_{t} = \theta_{t-1} + (\rho_t - \theta_{t-1}) /
    \min(t + 1, M)`; the projected set is convex, so the average stays in it.

    After each :meth:`step`, :attr:`last_info` records ``step`` (count), ``grad_norm`` (of
    the masked gradient), ``grad_norm_scaled`` (of the masked gradient times ``scale``: the
    gradient with respect to theta measured in its parts' typical magnitudes, which does not
    depend on their units), ``raw_step_norm``, ``step_norm`` (after clipping and the trust
    region), ``clipped``, ``projected`` (names like ``'phi1[2]'`` of the entries moved by the
    projection) and ``projection_norm``; with a step schedule also ``step_size`` (of this
    update), and with ``optimizer='natural'`` or ``max_policy_change`` (after :meth:`observe`)
    ``policy_change`` (the RMS change of the action, in MW, of the parameters in use) and
    ``trust_region`` (True if it shrank the step).
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
        groups: tuple[int, ...] | None = None,
    ) -> None:
        self.config = check_instance("config", config, LearningConfig)
        self.mask = learnable_mask(n, config.learn_constants)
        self.n = int(n)
        if isinstance(system_alpha, (tuple, list, np.ndarray)):
            alphas = tuple(check_real(f"system_alpha[{i}]", a, 0.0, low_open=True)
                           for i, a in enumerate(system_alpha))
            if len(alphas) != self.n:
                raise ValueError(f"system_alpha has {len(alphas)} values: expected n={self.n}")
            self.agent_alpha: tuple[float, ...] | None = alphas
            system_alpha = min(alphas)
        else:
            self.agent_alpha = None
        self.system_alpha = check_real("system_alpha", system_alpha, 0.0, low_open=True)
        self.groups = self._groups(groups)
        self.scale = self._scale_vector(scale or {}, price_scale)
        options: dict[str, Any] = {"scale": self.scale, "eps": eps,
                                   "damping": config.natural_damping}
        if config.optimizer == "adam" or betas != ADAM_BETAS:
            options["betas"] = betas
        self.rule: UpdateRule = make_update_rule(config.optimizer, len(PARTS) * self.n,
                                                 **options)
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
    def from_configs(cls, learning: LearningConfig, system: SystemConfig, prices: Any = None,
                     **kwargs: Any):
        """Build from the two configs (``n``, ``alpha`` and ``price_scale`` taken from
        ``system``). Where ``learning.scale_to_prices`` says so (:func:`scales_follow_prices`)
        the cost parts' scales follow the level of ``prices`` (the learning month's
        :class:`~mpcrl_lite.system.prices.Prices`, :func:`price_level`) instead of
        ``system.price_scale``."""
        if scales_follow_prices(learning, prices):
            if prices is None:
                raise ValueError("learning.scale_to_prices=True without the month's prices: "
                                 "expected prices= (the learning month's Prices)")
            kwargs.setdefault("price_scale", price_level(prices))
        kwargs.setdefault("price_scale", system.price_scale if system.price_scale > 0 else 1.0)
        terminal = learning.terminal_scale * kwargs["price_scale"]  # as part_scales scales
        kwargs.setdefault("scale", {"T1": terminal, "T2": terminal, "T3": terminal})
        kwargs.setdefault("groups", system.battery_groups())
        return cls(learning, system.n, system.alpha, **kwargs)

    def _groups(self, groups: Any) -> tuple[int, ...] | None:
        """The tying groups checked; None stands for one group of all agents."""
        if groups is None:
            return None
        groups = tuple(int(g) for g in groups)
        if len(groups) != self.n or sorted(set(groups)) != list(range(len(set(groups)))):
            raise ValueError(f"groups={groups!r}: expected one label per agent (n={self.n}), "
                             "numbered 0, 1, ...")
        return None if len(set(groups)) == 1 else groups

    def _scale_vector(self, scale: dict[str, float], price_scale: float) -> np.ndarray:
        unknown = set(scale) - set(PARTS)
        if unknown:
            raise ValueError(
                f"scale has unknown part(s) {sorted(unknown)}; expected some of {PARTS}"
            )
        parts = part_scales(self.system_alpha, price_scale)
        for name, value in scale.items():
            parts[name] = check_real(f"scale[{name!r}]", value, 0.0, low_open=True)
        vector = np.repeat([parts[name] for name in PARTS], self.n)
        if self.agent_alpha is not None:  # each agent's own alpha scales its model parts
            for name in ("alpha", "delta"):
                if name not in scale and DEFAULT_SCALE[name] is None:
                    vector[Theta.index(self.n, name)] = self.agent_alpha
        return vector

    # -- state ----------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the optimizer state (step count, the rule's state, e.g. Adam's moments,
        the raw iterate of the averaging and an observed metric)."""
        self.step_count = 0
        self.rule.reset()
        self.raw: np.ndarray | None = None
        self._metric: np.ndarray | None = None
        self.last_info: dict[str, Any] = {}

    def observe(self, grad_pi: np.ndarray) -> None:
        r"""Give the next :meth:`step` the month's metric
        :math:`F = \mathbb E[\nabla_\theta\pi\nabla_\theta\pi^\top]` (:func:`policy_metric`)
        of the samples its gradient was estimated from.

        Needed by ``optimizer='natural'`` and ``max_policy_change``; otherwise it only adds
        ``policy_change`` to :attr:`last_info`. The metric is used by one step.

        Parameters
        ----------
        grad_pi : array, shape ``(..., 10 n, n)``
        """
        metric = policy_metric(grad_pi)
        if metric.shape != (self.mask.size, self.mask.size):
            raise ValueError(f"grad_pi has shape {np.shape(grad_pi)}; expected "
                             f"(..., {self.mask.size}, n) (10 n rows of theta)")
        if not np.all(np.isfinite(metric)):
            raise ValueError("grad_pi contains non-finite values (nan or inf)")
        self._metric = np.where(np.outer(self.mask, self.mask), metric, 0.0)

    def state_dict(self) -> dict[str, Any]:
        """JSON-friendly state (lists, floats, ints, str): enough to resume exactly.

        Keys ``optimizer``, ``n``, ``step_count``, ``m`` and ``v`` for every rule (``m`` and
        ``v`` are Adam's moments, zeros for a rule that keeps none), so checkpoints of every
        rule, old and new, share one layout.
        """
        arrays = self.rule.state_arrays()
        zeros = np.zeros(len(PARTS) * self.n)
        state = {
            "optimizer": self.config.optimizer,
            "n": self.n,
            "step_count": int(self.step_count),
            **{key: arrays.get(key, zeros).tolist() for key in STATE_KEYS},
        }
        if self.config.average_months:  # the raw iterate, only when averaging
            state["theta_raw"] = None if self.raw is None else self.raw.tolist()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` (same optimizer and ``n`` required). ``theta_raw``
        (the averaging's raw iterate) is optional: without it the averaging restarts from
        the parameters of the next step."""
        expected = {"optimizer", "n", "step_count", *STATE_KEYS}
        if not expected <= set(state) <= expected | {"theta_raw"}:
            raise ValueError(f"state has keys {sorted(state)}; expected {sorted(expected)} "
                             "(and optionally 'theta_raw')")
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
        raw = state.get("theta_raw")
        if raw is not None:
            raw = np.asarray(raw, dtype=float)
            if raw.shape != (size,) or not np.all(np.isfinite(raw)):
                raise ValueError(f"state 'theta_raw' has shape {raw.shape}; expected ({size},) "
                                 "finite numbers")
        self.step_count = count
        self.rule.load_state_arrays(moments)
        self.raw = raw

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
        config = self.config
        metric = self._metric
        if config.tie_agents:  # the gradient and metric of the shared parameters
            g = self._tie(g)
            if metric is not None:
                metric = self._tie(self._tie(metric).T).T
        if metric is None and not g.any():
            metric = np.zeros((g.size, g.size))  # nothing was learned: no metric is needed
        if metric is None and (self.rule.NEEDS_METRIC or config.max_policy_change):
            raise ValueError(
                f"optimizer={config.optimizer!r}, max_policy_change="
                f"{config.max_policy_change!r}: the step needs the month's metric; call "
                "observe(grad_pi) first"
            )
        self.step_count += 1
        direction = self.rule.direction(g, self.step_count, metric=metric)
        if config.tie_agents:  # exactly, not only up to the rounding of a solve
            direction = self._tie(direction)
        step_size = config.step_size
        if config.step_warmup:
            step_size *= min(1.0, self.step_count / config.step_warmup)
        if config.step_decay:
            step_size /= 1.0 + (self.step_count - 1) / config.step_decay
        step = step_size * direction
        raw_norm = float(np.linalg.norm(step))
        clip = config.grad_clip
        clipped = clip is not None and raw_norm > clip
        if clipped:
            step = step * (clip / raw_norm)
        shrunk = False
        if config.max_policy_change and metric is not None:
            change = float(np.sqrt(max(step @ metric @ step, 0.0)))
            shrunk = change > config.max_policy_change
            if shrunk:
                step = step * (config.max_policy_change / change)
        limited = 1.0
        if config.step_limit:  # the longest move, in units of each entry's scale
            reach = float(np.max(np.abs(step) / self.scale))
            if reach > config.step_limit:
                limited = config.step_limit / reach
                step = step * limited
        current = theta.to_vector()
        start = current if self.raw is None or not config.average_months else self.raw
        moved = start - step
        raw = np.maximum(moved, self._lower) if config.keep_well_posed else moved
        hit = raw != moved
        if config.reset_momentum_at_bounds and hit.any() and "m" in self.rule.STATE:
            self.rule.m[hit] = 0.0  # no momentum into a bound the projection holds
        if config.average_months:
            self.raw = raw
            new = current + (raw - current) / min(self.step_count + 1, config.average_months)
        else:
            new = raw
        self.last_info = {
            "step": self.step_count,
            "grad_norm": float(np.linalg.norm(g)),
            "grad_norm_scaled": float(np.linalg.norm(self.scale * g)),
            "raw_step_norm": raw_norm,
            "step_norm": float(np.linalg.norm(step)),
            "clipped": bool(clipped),
            "projected": [name for name, h in zip(self._names, hit) if h],
            "projection_norm": float(np.linalg.norm(raw - moved)),
        }
        # the keys of the options, only where they are used (histories of runs without them
        # keep the keys they always had)
        if config.step_warmup or config.step_decay:
            self.last_info["step_size"] = float(step_size)
        if config.step_limit:
            self.last_info["step_limited"] = float(limited)
        if self._metric is not None and (self.rule.NEEDS_METRIC or config.max_policy_change):
            change = new - current
            self.last_info["policy_change"] = float(np.sqrt(max(change @ self._metric @ change,
                                                                0.0)))
            self.last_info["trust_region"] = bool(shrunk)
        self._metric = None
        return Theta.from_vector(new, self.n)

    def effective_gradient(self, grad: np.ndarray) -> np.ndarray:
        """The gradient as the update rule sees it: zero outside :attr:`mask` and, with
        ``tie_agents``, each part's mean over the agents; shape ``(10 n,)``."""
        grad = np.asarray(grad, dtype=float)
        if grad.shape != self.mask.shape:
            raise ValueError(f"grad has shape {grad.shape}; expected {self.mask.shape} (10 n)")
        g = np.where(self.mask, grad, 0.0)
        return self._tie(g) if self.config.tie_agents else g

    def _tie(self, x: np.ndarray) -> np.ndarray:
        """The mean over the agents of a group of each part, for every agent of the group: the
        orthogonal projection onto parameters shared within the groups (along axis 0 of
        ``x``, shape ``(10 n, ...)``)."""
        parts = x.reshape((len(PARTS), self.n) + x.shape[1:])
        if self.groups is None:  # one group
            return np.broadcast_to(parts.mean(axis=1, keepdims=True),
                                   parts.shape).reshape(x.shape)
        out = np.empty_like(parts)
        labels = np.asarray(self.groups)
        for g in range(labels.max() + 1):
            members = labels == g
            out[:, members] = parts[:, members].mean(axis=1, keepdims=True)
        return out.reshape(x.shape)

    def __repr__(self) -> str:
        c = self.config
        return (
            f"DPGUpdater(optimizer={c.optimizer!r}, step_size={c.step_size:g}, n={self.n}, "
            f"learnable={int(self.mask.sum())}/{self.mask.size}, step_count={self.step_count})"
        )
