r"""Update rules of the actor: how a policy gradient becomes a direction for theta.

:class:`~mpcrl_lite.learning.dpg.DPGUpdater` does everything around the rule -- the mask of learnable
entries, the step size, clipping, the projection, the record of each step -- and asks an
:class:`UpdateRule` for one thing: the direction :math:`d_t` of the step
:math:`\theta \leftarrow \theta - \alpha\,d_t` from the masked gradient :math:`g_t`.

* :class:`GradientDescent` (``'sgd'``): :math:`d_t = g_t`, the paper's rule.
* :class:`Adam` (``'adam'``): per-entry normalised moments times a typical magnitude per
  entry (see :mod:`mpcrl_lite.learning.dpg`).
* :class:`NaturalGradient` (``'natural'``): the natural gradient
  :math:`F^{-1} g_t` in the metric of the policy's actions,
  :math:`F = \mathbb E[\nabla_\theta\pi\,\nabla_\theta\pi^\top]`, with momentum and a
  normalisation that makes the step size the RMS change of the action in MW. With the
  compatible critic, :math:`F^{-1} g_t` is the critic's own weight vector :math:`w`.

Adding a rule adds a subclass and an entry of :data:`UPDATE_RULES`, keyed by its name in
:data:`mpcrl_lite.config.OPTIMIZERS` (the names ``LearningConfig.optimizer`` accepts). A rule
that needs the metric :math:`F` of the month (:attr:`UpdateRule.NEEDS_METRIC`) gets it as
``direction(g, t, metric=F)``.

A rule's state is at most two arrays of theta's size, ``'m'`` and ``'v'`` (first and second
moment estimates): the checkpoint layout of :meth:`~mpcrl_lite.learning.dpg.DPGUpdater.state_dict`
has both for every rule, zeros where a rule keeps none.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from .._util.validate import check_choice, check_real

__all__ = [
    "ADAM_BETAS",
    "ADAM_EPS",
    "ADAM_STEP_SIZE",
    "NATURAL_BETAS",
    "NATURAL_DAMPING",
    "STATE_KEYS",
    "UPDATE_RULES",
    "Adam",
    "GradientDescent",
    "NaturalGradient",
    "UpdateRule",
    "make_update_rule",
    "natural_direction",
]

#: Adam's moment decay rates (beta1, beta2), the usual defaults.
ADAM_BETAS: tuple[float, float] = (0.9, 0.999)
#: Adam's denominator guard.
ADAM_EPS: float = 1e-8
#: A sensible ``LearningConfig.step_size`` for ``optimizer='adam'`` (the default): each
#: learnable entry moves by at most about 2 % of its scale per update (see :class:`Adam`).
#: Measured on the paper's system: 0.05 lets the first, noisiest months push
#: single batteries far in a wrong direction (one battery then keeps selling into the
#: penalised zone for tens of months, in 2 of 3 seeds); with 0.02 all 6 seeds tried
#: learned within 100 months.
ADAM_STEP_SIZE: float = 2e-2
#: Names of the state arrays a rule may keep (the checkpoint holds both, zeros if unused).
STATE_KEYS: tuple[str, ...] = ("m", "v")
#: :class:`NaturalGradient`'s decay rates of its momentum and of its scalar second moment.
NATURAL_BETAS: tuple[float, float] = (0.9, 0.999)
#: :class:`NaturalGradient`'s relative (Levenberg-Marquardt) damping of the metric:
#: :math:`F + \lambda\,\mathrm{diag}(F)`.
NATURAL_DAMPING: float = 1e-3



def _check_betas(betas: tuple[float, float]) -> tuple[float, float]:
    """The two moment decay rates of Adam-like rules, each in ``[0, 1)``, else an error."""
    if len(betas) != 2:
        raise ValueError(f"betas={betas!r}: expected two values in [0, 1)")
    return (check_real("betas[0]", betas[0], 0.0, 1.0, high_open=True),
            check_real("betas[1]", betas[1], 0.0, 1.0, high_open=True))


class UpdateRule:
    """Base class: turns the masked gradient into the direction of a step.

    Parameters
    ----------
    size : int
        Number of entries of theta (``10 n``).

    Notes
    -----
    Subclasses set :attr:`name`, may list the keyword arguments they take in
    :attr:`OPTIONS` (:func:`make_update_rule` passes only those), implement
    :meth:`direction`, and keep their state in the arrays named in :attr:`STATE`.
    """

    #: The rule's name in :data:`mpcrl_lite.config.OPTIMIZERS`.
    name: ClassVar[str] = ""
    #: Keyword arguments of the constructor beyond ``size``.
    OPTIONS: ClassVar[tuple[str, ...]] = ()
    #: Names (from :data:`STATE_KEYS`) of the state arrays the rule keeps.
    STATE: ClassVar[tuple[str, ...]] = ()
    #: The rule needs the metric :math:`F` of the month in :meth:`direction`.
    NEEDS_METRIC: ClassVar[bool] = False

    def __init__(self, size: int) -> None:
        self.size = int(size)
        self.reset()

    def reset(self) -> None:
        """Forget the state: every state array back to zeros."""
        for key in self.STATE:
            setattr(self, key, np.zeros(self.size))

    def direction(self, g: np.ndarray, t: int, metric: np.ndarray | None = None) -> np.ndarray:
        r"""The direction of step ``t`` (counted from 1) for the masked gradient ``g``.

        Parameters
        ----------
        g : array, shape ``(size,)``
            Gradient of J, zero outside the learnable entries.
        t : int
            Number of this step, 1 for the first.
        metric : array, shape ``(size, size)``, optional
            :math:`F = \mathbb E[\nabla_\theta\pi\,\nabla_\theta\pi^\top]` of the month
            (zero rows and columns outside the learnable entries); used by the rules with
            :attr:`NEEDS_METRIC`, ignored by the others.

        Returns
        -------
        array, shape ``(size,)``
            ``theta`` moves by ``-step_size`` times this (before clipping and projection).
        """
        raise NotImplementedError

    def step_size_warning(self, step_size: float) -> str | None:
        """Why ``step_size`` is probably not what the user meant with this rule, or ``None``."""
        return None

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The state arrays by name (the ones in :attr:`STATE`)."""
        return {key: getattr(self, key) for key in self.STATE}

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore :meth:`state_arrays` (shapes checked by the caller)."""
        for key in self.STATE:
            setattr(self, key, np.asarray(arrays[key], dtype=float))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(size={self.size})"


class GradientDescent(UpdateRule):
    r"""The paper's rule (paper eq. 12): the direction is the gradient itself,
    :math:`\theta \leftarrow \theta - \alpha\nabla_\theta J` (``step_size`` = the paper's
    :math:`\alpha`, 5e-8). No state."""

    name = "sgd"

    def direction(self, g: np.ndarray, t: int, metric: np.ndarray | None = None) -> np.ndarray:
        return g


class Adam(UpdateRule):
    r"""Adam with a typical magnitude per entry:

    .. math::

        m_t = \beta_1 m_{t-1} + (1-\beta_1) g_t, \quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2) g_t^2, \quad
        d_t = \sigma \odot \frac{m_t / (1-\beta_1^t)}{\sqrt{v_t / (1-\beta_2^t)} + \epsilon},

    with :math:`\sigma` the per-entry ``scale``. The direction is normalised (each entry is at
    most about 1 in units of its scale), so the step size is a *relative move per update*.
    Entries whose gradient is always zero keep zero moments and never move.

    Parameters
    ----------
    size : int
        Number of entries of theta.
    scale : array, shape ``(size,)``
        Typical magnitude :math:`\sigma` of each entry (finite, > 0).
    betas : (float, float), default :data:`ADAM_BETAS`
        Decay rates of the first and second moments, each in ``[0, 1)``.
    eps : float, default :data:`ADAM_EPS`
        Denominator guard, > 0.
    """

    name = "adam"
    OPTIONS = ("scale", "betas", "eps")
    STATE = ("m", "v")

    def __init__(
        self,
        size: int,
        scale: np.ndarray,
        betas: tuple[float, float] = ADAM_BETAS,
        eps: float = ADAM_EPS,
    ) -> None:
        self.betas = _check_betas(betas)
        self.eps = check_real("eps", eps, 0.0, low_open=True)
        self.scale = np.asarray(scale, dtype=float)
        if self.scale.shape != (int(size),):
            raise ValueError(f"scale has shape {self.scale.shape}; expected ({int(size)},)")
        super().__init__(size)

    def direction(self, g: np.ndarray, t: int, metric: np.ndarray | None = None) -> np.ndarray:
        b1, b2 = self.betas
        self.m = b1 * self.m + (1.0 - b1) * g
        self.v = b2 * self.v + (1.0 - b2) * g**2
        m_hat = self.m / (1.0 - b1**t)
        v_hat = self.v / (1.0 - b2**t)
        return self.scale * m_hat / (np.sqrt(v_hat) + self.eps)

    def step_size_warning(self, step_size: float) -> str | None:
        if step_size < 1e-4:
            return (
                f"step_size={step_size:g} with optimizer='adam': Adam's step size is a "
                f"relative move per update, so theta will hardly change; try {ADAM_STEP_SIZE:g}"
            )
        return None

    def __repr__(self) -> str:
        return f"Adam(size={self.size}, betas={self.betas}, eps={self.eps:g})"


def natural_direction(g: np.ndarray, metric: np.ndarray, damping: float = 0.0) -> np.ndarray:
    r"""The natural gradient :math:`(F + \lambda\,\mathrm{diag}(F))^{+} g`.

    Entries whose diagonal of :math:`F` is zero (the policy does not depend on them) get a
    zero direction. The system is solved in the coordinates scaled by
    :math:`\mathrm{diag}(F)^{-1/2}` (a unit diagonal), so the result does not depend on the
    units of theta's entries; a singular :math:`F` gets the minimum-norm least-squares
    solution there.

    Parameters
    ----------
    g : array, shape ``(p,)``
        The vanilla gradient.
    metric : array, shape ``(p, p)``
        :math:`F`, symmetric positive semi-definite.
    damping : float, default 0
        :math:`\lambda \ge 0`, relative to the diagonal.

    Returns
    -------
    array, shape ``(p,)``
        With the compatible critic (:math:`g = F w`) and :math:`\lambda = 0`, the part of
        :math:`w` that the policy's actions can see: :math:`w` itself when :math:`F` is
        regular.
    """
    g = np.asarray(g, dtype=float)
    metric = np.asarray(metric, dtype=float)
    p = g.shape[0]
    if g.shape != (p,) or metric.shape != (p, p):
        raise ValueError(f"metric has shape {metric.shape}; expected ({p}, {p}) to match g")
    damping = check_real("damping", damping, 0.0)
    diag = np.diag(metric).copy()
    live = diag > 0.0
    out = np.zeros(p)
    if live.any():
        root = np.sqrt(diag[live])
        scaled = metric[np.ix_(live, live)] / np.outer(root, root)
        scaled[np.diag_indices_from(scaled)] += damping
        x = np.linalg.lstsq(scaled, g[live] / root, rcond=None)[0]
        out[live] = x / root
    return out


class NaturalGradient(UpdateRule):
    r"""The natural gradient in the policy's action metric, with momentum, normalised:

    .. math::

        d_t = (F_t + \lambda\,\mathrm{diag}F_t)^{+} g_t, \quad
        m_t = \beta_1 m_{t-1} + (1-\beta_1) d_t, \quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2)\, d_t^\top F_t d_t, \quad
        \text{direction} = \frac{m_t / (1-\beta_1^t)}{\sqrt{v_t / (1-\beta_2^t)} + \epsilon},

    with :math:`F_t = \mathbb E[\nabla_\theta\pi\,\nabla_\theta\pi^\top]` of month ``t``.
    Since a change :math:`\Delta\theta` changes the actions by
    :math:`\nabla_\theta\pi^\top\Delta\theta`, :math:`\sqrt{\Delta\theta^\top F\Delta\theta}`
    is the RMS change of the action: a step of ``step_size`` times this direction changes
    the action by at most about ``step_size`` MW (RMS over the month's states) when the
    months agree, less when they do not (the momentum averages out). No per-part scale is
    needed: the rule is invariant to the units (any linear reparametrisation) of theta.

    With the compatible critic, :math:`g_t = F_t w_t`, so :math:`d_t` is the critic's
    weight vector :math:`w_t` and :math:`d_t^\top F_t d_t = w_t^\top g_t` the mean square
    of the critic's action gradient :math:`\nabla_\theta\pi^\top w_t`.

    Measured on the paper's system (``benchmarks/README.md``): it learns, but more slowly
    than the per-part Adam, and a battery whose action sits at a bound (tiny
    :math:`\nabla_\theta\pi`) gets large moves of theta for a small first-order change of its
    action; it is an option, not the default.

    Parameters
    ----------
    size : int
    betas : (float, float), default :data:`NATURAL_BETAS`
        Decay rates of the momentum and of the scalar second moment, each in ``[0, 1)``.
    damping : float, default :data:`NATURAL_DAMPING`
        :math:`\lambda`, the relative damping of :math:`F` (see :func:`natural_direction`).
    eps : float, default :data:`ADAM_EPS`
        Denominator guard (in the unit of the critic's action gradient, NOK/MWh per MW).

    Notes
    -----
    The scalar :math:`v_t` is kept in the state array ``'v'`` (every entry equal), so the
    checkpoint layout is the one of every rule.
    """

    name = "natural"
    OPTIONS = ("betas", "damping", "eps")
    STATE = ("m", "v")
    NEEDS_METRIC = True

    def __init__(
        self,
        size: int,
        betas: tuple[float, float] = NATURAL_BETAS,
        damping: float = NATURAL_DAMPING,
        eps: float = ADAM_EPS,
    ) -> None:
        self.betas = _check_betas(betas)
        self.damping = check_real("damping", damping, 0.0)
        self.eps = check_real("eps", eps, 0.0, low_open=True)
        super().__init__(size)

    def direction(self, g: np.ndarray, t: int, metric: np.ndarray | None = None) -> np.ndarray:
        if metric is None:
            raise ValueError(
                "metric=None: the natural gradient needs the month's metric "
                "F = E[grad_pi grad_pi^T] (DPGUpdater.observe(grad_pi) before step)"
            )
        b1, b2 = self.betas
        d = natural_direction(g, metric, self.damping)
        self.m = b1 * self.m + (1.0 - b1) * d
        self.v = b2 * self.v + (1.0 - b2) * float(d @ metric @ d)
        m_hat = self.m / (1.0 - b1**t)
        v_hat = float(self.v[0]) / (1.0 - b2**t) if self.size else 0.0
        return m_hat / (np.sqrt(v_hat) + self.eps)

    def step_size_warning(self, step_size: float) -> str | None:
        if step_size < 1e-4 or step_size > 0.5:
            return (
                f"step_size={step_size:g} with optimizer='natural': the step size is the RMS "
                "change of the action per update in MW; try 0.02"
            )
        return None

    def __repr__(self) -> str:
        return (f"NaturalGradient(size={self.size}, betas={self.betas}, "
                f"damping={self.damping:g}, eps={self.eps:g})")


#: Every update rule by its name; the keys are :data:`mpcrl_lite.config.OPTIMIZERS`.
UPDATE_RULES: dict[str, type[UpdateRule]] = {
    rule.name: rule for rule in (GradientDescent, Adam, NaturalGradient)
}


def make_update_rule(name: str, size: int, **options: Any) -> UpdateRule:
    """The rule called ``name``, built with the ``options`` it takes (others are ignored).

    Parameters
    ----------
    name : str
        One of :data:`UPDATE_RULES` (``LearningConfig.optimizer``).
    size : int
        Number of entries of theta.
    **options
        Keyword arguments offered to every rule, e.g. ``scale``, ``betas``, ``eps``; each
        rule takes those listed in its :attr:`UpdateRule.OPTIONS`.
    """
    rule = UPDATE_RULES[check_choice("optimizer", name, tuple(UPDATE_RULES))]
    return rule(size, **{key: value for key, value in options.items() if key in rule.OPTIONS})
