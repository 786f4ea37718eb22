r"""The learning step of a month: the LSTD critic and the deterministic policy gradient.

From a month of transitions (:class:`~mpcrl_lite.sim.record.MonthRecord`) the critic is the
compatible action-value function (paper, eq. 15)

.. math::
   Q_w(s, a) = (a - \pi_\theta(s))^\top \nabla_\theta\pi_\theta(s)^\top w + V_v(s),

fitted by LSTD on the samples whose MPC and sensitivity were usable
(:func:`mpcrl_lite.learning.lstd.lstd_q`; every day is an episode, its last hour does not bootstrap),
and the policy gradient is :math:`\widehat{\nabla_\theta J} = \frac1M\sum
\nabla_\theta\pi_\theta(s)\nabla_\theta\pi_\theta(s)^\top w` (eq. 13,
:func:`mpcrl_lite.learning.dpg.policy_gradient`): :func:`lstd_policy_gradient`. The centralized learner
applies it to all batteries with the stage cost :math:`\tilde L`, the decentralized one to
each battery with its own cost :math:`\tilde L_i` and its own soc.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..config import LearningConfig
from .dpg import policy_gradient
from .lstd import compatible_features, lstd_q, value_baseline_features

__all__ = ["lstd_policy_gradient"]


def lstd_policy_gradient(
    soc: np.ndarray,
    a: np.ndarray,
    policy: np.ndarray,
    grad_pi: np.ndarray,
    cost: np.ndarray,
    use: np.ndarray,
    learning: LearningConfig,
    gamma: float,
    buy: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """LSTD critic and policy gradient of one month (see the module docstring).

    Parameters
    ----------
    soc : (H+1, D, m)
        State of charge of the ``m`` batteries the policy acts for.
    a, policy : (H, D, m)
        Commanded action and the policy's action.
    grad_pi : (H, D, n_theta, m)
        :math:`\\nabla_\\theta\\pi_\\theta(s_k)`.
    cost : (H, D)
        Stage cost of the learner (all batteries', or one battery's own).
    use : (H, D) bool
        Samples whose MPC and sensitivity were usable.
    learning : LearningConfig
        ``value_features`` and ``ridge``.
    gamma : float
    buy : (H, D), optional
        The month's buy prices, read by the value features that use them
        (``'hour*paper+price'``).

    Returns
    -------
    grad : (n_theta,)
        Zero when no sample is usable.
    info : dict
        ``lstd_condition``, ``lstd_rank_deficient``, ``td_rms``, ``samples`` (or
        ``{"lstd": "no usable samples"}``).
    """
    if not use.any():
        return np.zeros(grad_pi.shape[2]), {"lstd": "no usable samples"}
    H = cost.shape[0]
    features = value_baseline_features(soc, learning.value_features, buy)
    phi, phi_next = features[:-1], features[1:]
    psi = compatible_features(grad_pi, a, policy)
    done = np.broadcast_to((np.arange(H) == H - 1)[:, None], use.shape)
    every = use.all()  # then the arrays themselves, in the order use would take them

    def usable(array: np.ndarray) -> np.ndarray:
        return array if every else array[use]

    fit = lstd_q(usable(phi), usable(psi), usable(cost), usable(phi_next), gamma,
                 done=usable(done), ridge=learning.ridge)
    grad = policy_gradient(usable(grad_pi), fit.w)
    info = {
        "lstd_condition": float(fit.condition),
        "lstd_rank_deficient": bool(fit.rank_deficient),
        "td_rms": float(fit.td_rms),
        "samples": int(fit.n_samples),
    }
    return grad, info
