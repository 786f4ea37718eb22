"""The true battery system: dynamics with noise, the low-level controller, and the costs.

Everything here is plain numpy and works on a batch of independent days at once. The
arrays are laid out as

* ``(days, n)`` -- one entry per day of the batch and per battery (agent);
* ``(days,)``   -- one entry per day (prices at the current hour, totals over agents);
* ``(hours, days, ...)`` -- a whole day, hour by hour (the closed loop of
  :mod:`mpcrl_lite.sim.closed_loop` runs a policy on this system and records every hour).

The equations (paper, Section II and the low-level control)
------------------------------------------------------------
Dynamics of battery ``i`` over the hour ``[k, k+1]``::

    soc_{k+1} = soc_k + alpha (Delta_k + b_k - s_k),     Delta_k ~ N(noise_mean, noise_var)

with the commanded input ``a = b - s`` (at an optimum ``b`` and ``s`` are never both
non-zero, so the net power ``a`` is all that matters). Without intervention the state could
leave the physical range ``[0, 1]``; a fast **low-level controller** then changes the power
exchanged with the grid just enough to stop at the edge (see :func:`low_level_control`).

Per-agent stage cost, with the prices ``phi_b`` (buy) and ``phi_s`` (sell) of the hour::

    L(b, s)        = phi_b b - phi_s s
    penalty(soc)   = p max(soc - soc_high, 0) + p max(soc_low - soc, 0)
    L~_i           = L(b_i, s_i) + penalty(soc_i)
    L~(s_k, a_k)   = sum_i L~_i                          (the centralised stage cost)

and the power exchanged with the main grid at the connection point::

    P_k = max(sum_i b_i, sum_i s_i).

The closed-loop performance of a day is ``J = E[sum_k gamma^k L~(s_k, a_k)]``
(:func:`discounted_return`, :meth:`mpcrl_lite.sim.record.Record.J`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import SystemConfig

__all__ = [
    "StepResult",
    "agent_costs",
    "battery_values",
    "discounted_return",
    "grid_power",
    "low_level_control",
    "penalty",
    "project_action",
    "sample_noise",
    "split_action",
    "step",
    "step_unchecked",
    "unchecked_penalty",
]

# -- input checks ---------------------------------------------------------------------------
def _as_float_array(name: str, value: Any) -> np.ndarray:
    """``value`` as a float array whose entries are all finite, or a ValueError naming it."""
    if np.iscomplexobj(value):
        raise ValueError(f"{name}: expected real numbers, got complex values")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"{name}={value!r}: expected an array of real numbers ({exc})"
        ) from None
    bad = ~np.isfinite(arr)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        where = f"[{', '.join(map(str, index))}]" if index else ""
        raise ValueError(f"{name}{where}={arr[index]!r}: expected finite values only")
    return arr


def _batch(name: str, value: Any, n: int) -> np.ndarray:
    """A finite float array of shape ``(days, n)``."""
    arr = _as_float_array(name, value)
    if arr.ndim != 2 or arr.shape[1] != n:
        raise ValueError(f"{name} has shape {arr.shape}: expected (days, n) = (days, {n})")
    return arr


def _same_shape(name: str, arr: np.ndarray, ref_name: str, ref: np.ndarray) -> None:
    if arr.shape != ref.shape:
        raise ValueError(
            f"{name} has shape {arr.shape}: expected the shape of {ref_name}, {ref.shape}"
        )


def _batches_like_soc(n: int, soc: Any, **others: Any) -> list[np.ndarray]:
    """``soc`` and the named ``others`` as finite ``(days, n)`` arrays, in that order, the
    others of exactly soc's shape (all shapes are checked before any comparison)."""
    arrays = [_batch("soc", soc, n)] + [_batch(name, value, n) for name, value in others.items()]
    for name, arr in zip(others, arrays[1:]):
        _same_shape(name, arr, "soc", arrays[0])
    return arrays


def _nonnegative(name: str, arr: np.ndarray) -> None:
    if (arr < 0).any():
        index = tuple(int(i) for i in np.argwhere(arr < 0)[0])
        raise ValueError(
            f"{name}[{', '.join(map(str, index))}]={arr[index]!r}: expected powers >= 0"
        )


def _soc_in_range(name: str, soc: np.ndarray) -> None:
    outside = (soc < 0.0) | (soc > 1.0)
    if outside.any():
        index = tuple(int(i) for i in np.argwhere(outside)[0])
        raise ValueError(
            f"{name}[{', '.join(map(str, index))}]={soc[index]!r}: "
            "expected a state of charge in [0, 1]"
        )


def _day_prices(name: str, value: Any, days: int) -> np.ndarray:
    """Prices of one hour, one per day: shape ``(days,)`` (a scalar is used for every day)."""
    arr = _as_float_array(name, value)
    if arr.ndim == 0:
        arr = np.full(days, float(arr))
    if arr.shape != (days,):
        raise ValueError(f"{name} has shape {arr.shape}: expected (days,) = ({days},)")
    return arr


def _check_system(system: Any) -> None:
    # bad input of any kind is a ValueError in this package, wrong types included
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004


def battery_values(system: SystemConfig, name: str) -> float | np.ndarray:
    """A per-battery field of ``system`` (:data:`~mpcrl_lite.config.PER_BATTERY`) for array
    arithmetic over ``(..., n)``: the float itself when it is one value for all batteries (so
    identical batteries compute exactly as with a scalar), else an array of shape ``(n,)``.
    ``'noise_std'`` gives the standard deviation of the noise."""
    value = system.noise_std if name == "noise_std" else getattr(system, name)
    return np.array(value, dtype=float) if isinstance(value, tuple) else value


# -- noise and inputs -----------------------------------------------------------------------
def sample_noise(
    rng: np.random.Generator, shape: int | tuple[int, ...], system: SystemConfig
) -> np.ndarray:
    """Draw the production-demand noise ``Delta ~ N(noise_mean, noise_var)``.

    Every entry is independent (one per day and agent when ``shape = (days, n)``); the
    standard deviation is ``sqrt(noise_var)``, since Table I's second argument is a variance.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness; one call to ``rng.normal`` with ``size=shape`` is made.
    shape : int or tuple of int
        Shape of the draw, usually ``(days, n)``.
    system : SystemConfig
        Provides ``noise_mean`` and ``noise_var``.

    Returns
    -------
    numpy.ndarray
        Noise of the given shape.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError(  # noqa: TRY004
            f"rng={rng!r}: expected a numpy.random.Generator (np.random.default_rng)"
        )
    _check_system(system)
    dims = (shape,) if isinstance(shape, (int, np.integer)) else tuple(shape)
    for d in dims:
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d < 0:
            raise ValueError(f"shape={shape!r}: expected non-negative integers")
    mean, std = battery_values(system, "noise_mean"), battery_values(system, "noise_std")
    if (np.ndim(mean) or np.ndim(std)) and (not dims or dims[-1] != system.n):
        raise ValueError(f"shape={shape!r}: the noise differs between batteries; expected a "
                         f"shape ending in n={system.n}")
    return rng.normal(mean, std, size=dims)


def split_action(a: Any) -> tuple[np.ndarray, np.ndarray]:
    """Split a net power into buying and selling: ``b = max(a, 0)``, ``s = max(-a, 0)``.

    The paper's input is ``a = b - s``; since buying and selling at once is never optimal,
    the split with at most one of ``b``, ``s`` non-zero is the one used here.

    Parameters
    ----------
    a : array_like, any shape (usually ``(days, n)``)
        Net power, positive when buying.

    Returns
    -------
    b, s : numpy.ndarray
        Non-negative arrays of the shape of ``a`` with ``b - s == a``.
    """
    a = _as_float_array("a", a)
    return np.maximum(a, 0.0), np.maximum(-a, 0.0)


def _project_capped_simplex(y: np.ndarray, upper: float, total: float) -> np.ndarray:
    """Row-wise Euclidean projection of ``y >= 0`` (shape ``(days, n)``) onto
    ``{x : 0 <= x_i <= upper, sum_i x_i <= total}``.

    The KKT conditions give ``x = clip(y - tau, 0, upper)`` with ``tau = 0`` when the sum
    constraint is slack, else the unique ``tau > 0`` solving
    ``g(tau) = sum_i clip(y_i - tau, 0, upper) = total``. ``g`` is piecewise linear and
    non-increasing with kinks at ``y_i`` and ``y_i - upper``; evaluating it at the sorted
    kinks brackets the root between two neighbours, where it is found exactly by linear
    interpolation. Cost: ``O(days n^2)`` memory and time, no loop over days.
    """
    clipped = np.minimum(y, upper)
    active = clipped.sum(axis=-1) > total
    if not active.any():
        return clipped
    kinks = np.sort(np.concatenate([y - upper, y], axis=-1), axis=-1)  # (days, 2n)
    g = np.clip(y[:, None, :] - kinks[:, :, None], 0.0, upper).sum(axis=-1)  # (days, 2n)
    # g at the smallest kink is n * upper > total on active rows and 0 at the largest,
    # so the first kink with g <= total has index >= 1 there.
    j = np.maximum(np.argmax(g <= total, axis=-1), 1)[:, None]
    t0, t1 = np.take_along_axis(kinks, j - 1, -1), np.take_along_axis(kinks, j, -1)
    g0, g1 = np.take_along_axis(g, j - 1, -1), np.take_along_axis(g, j, -1)
    slope = np.where(active[:, None], g0 - g1, 1.0)  # avoid 0/0 on rows left unchanged
    tau = t0 + (g0 - total) * (t1 - t0) / slope
    return np.where(active[:, None], np.clip(y - tau, 0.0, upper), clipped)


def project_action(a: Any, system: SystemConfig) -> np.ndarray:
    """Euclidean projection of net powers onto the feasible input set.

    Solves, for every day independently::

        min_x ||x - a||^2   s.t.  -U_bar <= x_i <= U_bar,
                                  sum_i max(x_i, 0) <= P_bar,   sum_i max(-x_i, 0) <= P_bar.

    The solution never changes the sign of an entry, so the problem splits into two
    independent projections of ``max(a, 0)`` and ``max(-a, 0)`` onto the capped simplex
    ``{0 <= y_i <= U_bar, sum_i y_i <= P_bar}``, each of the form ``clip(y - tau, 0, U_bar)``
    with a threshold ``tau >= 0`` found exactly (no iteration, no loop over days).

    Parameters
    ----------
    a : array_like, shape ``(days, n)``
        Net powers (e.g. an MPC action plus exploration noise).
    system : SystemConfig
        Provides ``n``, ``U_bar`` and ``P_bar``.

    Returns
    -------
    numpy.ndarray, shape ``(days, n)``
        The closest feasible net powers; ``a`` itself when it is already feasible.
    """
    _check_system(system)
    a = _batch("a", a, system.n)
    buy, sell = split_action(a)
    U = battery_values(system, "U_bar")
    return _project_capped_simplex(buy, U, system.P_bar) - _project_capped_simplex(
        sell, U, system.P_bar
    )


# -- dynamics -------------------------------------------------------------------------------
def low_level_control(
    soc: Any, a: Any, noise: Any, system: SystemConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The low-level controller: the powers actually exchanged so that soc stays in [0, 1].

    The commanded net power ``a = b - s`` would give the raw next state
    ``soc + alpha (Delta + a)``. The controller leaves ``a`` unchanged when that stays in
    ``[0, 1]``; otherwise it moves the net power just enough to stop at the edge::

        net = clip(a, (0 - soc)/alpha - Delta, (1 - soc)/alpha - Delta)
        b_applied = max(net, 0),  s_applied = max(-net, 0),  correction = net - a.

    Above 1 it therefore first buys less and, if that is not enough, sells extra; below 0
    it first sells less and then buys extra.

    **Safety first:** the applied powers are *not* limited by ``U_bar`` or ``P_bar``. A large
    production surplus or demand is absorbed by the grid whatever the bounds say, so the
    applied ``b``, ``s`` and the grid power ``P_k`` may exceed the limits the MPC respects.

    The decision is taken on the raw next state as computed in floating point: when it lies
    in ``[0, 1]`` the correction is exactly zero (rounding never nudges an inside step).

    Parameters
    ----------
    soc : array_like, shape ``(days, n)``
        State of charge at hour k, in ``[0, 1]``.
    a : array_like, shape ``(days, n)``
        Commanded net power (any finite value; the controller does not project it).
    noise : array_like, shape ``(days, n)``
        Production-demand noise ``Delta_k``.
    system : SystemConfig
        Provides ``alpha`` and ``n``.

    Returns
    -------
    b_applied, s_applied : numpy.ndarray, shape ``(days, n)``
        Power bought and sold, non-negative, never both non-zero.
    correction : numpy.ndarray, shape ``(days, n)``
        ``(b_applied - s_applied) - a``: positive when the controller bought extra (or sold
        less), negative when it bought less (or sold extra), zero when it did nothing.
    """
    _check_system(system)
    soc, a, noise = _low_level_inputs(soc, a, noise, system)
    net, _ = _apply_controller(soc, a, noise, battery_values(system, "alpha"))
    return np.maximum(net, 0.0), np.maximum(-net, 0.0), net - a


def _low_level_inputs(
    soc: Any, a: Any, noise: Any, system: SystemConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    soc, a, noise = _batches_like_soc(system.n, soc, a=a, noise=noise)
    _soc_in_range("soc", soc)
    return soc, a, noise


def _apply_controller(
    soc: np.ndarray, a: np.ndarray, noise: np.ndarray, alpha: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Applied net power and the next soc (both ``(days, n)``) for already checked inputs."""
    # Huge (finite) inputs may overflow to +-inf in the raw state; clipping handles that.
    with np.errstate(over="ignore", invalid="ignore"):
        raw = soc + alpha * (noise + a)
        upper = (1.0 - soc) / alpha - noise
        lower = (0.0 - soc) / alpha - noise
        # min/max keep the correction's sign right when raw is just past an edge by rounding
        net = np.where(raw > 1.0, np.minimum(a, upper), a)
        net = np.where(raw < 0.0, np.maximum(a, lower), net)
    # The next state is computed from raw, not from net: soc + alpha (Delta + net) would
    # lose the state to cancellation when Delta and net are huge and opposite.
    return net, np.clip(raw, 0.0, 1.0)


def penalty(soc: Any, system: SystemConfig) -> np.ndarray:
    """Penalty on soc outside the safe band, elementwise.

    ``penalty(soc) = p max(soc - soc_high, 0) + p max(soc_low - soc, 0)``; e.g. with
    ``p = 1000`` and ``soc_low = 0.1``, ``penalty(0.05) = 50``.

    Parameters
    ----------
    soc : array_like, any shape
    system : SystemConfig
        Provides ``p``, ``soc_low`` and ``soc_high``.

    Returns
    -------
    numpy.ndarray, shape of ``soc``
    """
    _check_system(system)
    return unchecked_penalty(_as_float_array("soc", soc), system)


def unchecked_penalty(soc: np.ndarray, system: SystemConfig) -> np.ndarray:
    """:func:`penalty` of a float array without the input checks, for hot loops (the causal
    dynamic program's grids)."""
    p = battery_values(system, "p")  # per battery: soc of shape (..., n)
    return p * np.maximum(soc - system.soc_high, 0.0) + p * np.maximum(system.soc_low - soc, 0.0)


def agent_costs(
    soc: Any, b: Any, s: Any, buy_price: Any, sell_price: Any, system: SystemConfig
) -> np.ndarray:
    """Per-agent stage cost ``L~_i = phi_b b_i - phi_s s_i + penalty(soc_i)``: the economic
    cost of paper eq. 2 plus the penalties of eq. 3 (whose sum over batteries is ``L~``).

    Parameters
    ----------
    soc : array_like, shape ``(days, n)``
        State of charge at which the penalty is charged (the state *before* the step).
    b, s : array_like, shape ``(days, n)``
        Powers bought and sold (non-negative).
    buy_price, sell_price : array_like, shape ``(days,)`` or scalar
        ``phi_b`` and ``phi_s`` of the hour, one per day and the same for every agent.
    system : SystemConfig

    Returns
    -------
    numpy.ndarray, shape ``(days, n)``
    """
    _check_system(system)
    soc, b, s = _batches_like_soc(system.n, soc, b=b, s=s)
    _nonnegative("b", b)
    _nonnegative("s", s)
    days = soc.shape[0]
    phi_b = _day_prices("buy_price", buy_price, days)
    phi_s = _day_prices("sell_price", sell_price, days)
    return _agent_costs(soc, b, s, phi_b, phi_s, system)


def _agent_costs(
    soc: np.ndarray, b: np.ndarray, s: np.ndarray, phi_b: np.ndarray, phi_s: np.ndarray,
    system: SystemConfig,
) -> np.ndarray:
    """``L~_i`` of checked inputs: ``(days, n)`` states and powers, ``(days,)`` prices."""
    return phi_b[:, None] * b - phi_s[:, None] * s + penalty(soc, system)


def grid_power(b: Any, s: Any) -> np.ndarray:
    """Power exchanged with the main grid, ``P_k = max(sum_i b_i, sum_i s_i)`` (paper eq. 6).

    Parameters
    ----------
    b, s : array_like, shape ``(days, n)``
        Powers bought and sold (non-negative).

    Returns
    -------
    numpy.ndarray, shape ``(days,)``
    """
    b = _as_float_array("b", b)
    s = _as_float_array("s", s)
    if b.ndim != 2:
        raise ValueError(f"b has shape {b.shape}: expected (days, n)")
    _same_shape("s", s, "b", b)
    _nonnegative("b", b)
    _nonnegative("s", s)
    return np.maximum(b.sum(axis=-1), s.sum(axis=-1))


@dataclass(frozen=True, eq=False)
class StepResult:
    """One hour of the true system for a batch of days (see :func:`step`).

    Attributes
    ----------
    soc_next : numpy.ndarray, shape ``(days, n)``
        State of charge at hour k+1, in ``[0, 1]``.
    b, s : numpy.ndarray, shape ``(days, n)``
        Powers actually bought and sold (after the low-level controller).
    correction : numpy.ndarray, shape ``(days, n)``
        Applied minus commanded net power.
    agent_cost : numpy.ndarray, shape ``(days, n)``
        ``L~_i`` at the state before the step and the applied powers.
    stage_cost : numpy.ndarray, shape ``(days,)``
        ``L~(s_k, a_k) = sum_i L~_i``.
    grid_power : numpy.ndarray, shape ``(days,)``
        ``P_k`` of the applied powers.
    """

    soc_next: np.ndarray
    b: np.ndarray
    s: np.ndarray
    correction: np.ndarray
    agent_cost: np.ndarray
    stage_cost: np.ndarray
    grid_power: np.ndarray


def step(
    soc: Any, a: Any, noise: Any, buy_price: Any, sell_price: Any, system: SystemConfig
) -> StepResult:
    """Advance the true system by one hour (paper eq. 1).

    ``soc_{k+1} = soc_k + alpha (Delta_k + b_k - s_k)`` with the powers ``b_k``, ``s_k`` of
    the low-level controller (:func:`low_level_control`). The hour is charged
    ``L~_i = phi_b b_i - phi_s s_i + penalty(soc_k,i)``: the penalty uses the state *before*
    the step, the economic part the applied powers at the current prices.

    Parameters
    ----------
    soc : array_like, shape ``(days, n)``
        State of charge at hour k, in ``[0, 1]``.
    a : array_like, shape ``(days, n)``
        Commanded net power.
    noise : array_like, shape ``(days, n)``
        ``Delta_k``.
    buy_price, sell_price : array_like, shape ``(days,)`` or scalar
        Prices of hour k.
    system : SystemConfig

    Returns
    -------
    StepResult
    """
    _check_system(system)
    soc, a, noise = _low_level_inputs(soc, a, noise, system)
    days = soc.shape[0]
    phi_b = _day_prices("buy_price", buy_price, days)
    phi_s = _day_prices("sell_price", sell_price, days)
    return step_unchecked(soc, a, noise, phi_b, phi_s, system)


def step_unchecked(
    soc: np.ndarray,
    a: np.ndarray,
    noise: np.ndarray,
    phi_b: np.ndarray,
    phi_s: np.ndarray,
    system: SystemConfig,
) -> StepResult:
    """:func:`step` without the input checks, for the closed loop's hours
    (:func:`mpcrl_lite.sim.closed_loop.simulate`), whose inputs are checked once or are finite
    by construction: ``soc`` float ``(days, n)`` in ``[0, 1]``, ``a`` and ``noise`` finite
    float ``(days, n)``, ``phi_b`` and ``phi_s`` finite float ``(days,)``. The same
    arithmetic as :func:`step`, so the same result to the last bit."""
    net, soc_next = _apply_controller(soc, a, noise, battery_values(system, "alpha"))
    b, s = np.maximum(net, 0.0), np.maximum(-net, 0.0)
    cost = _agent_costs(soc, b, s, phi_b, phi_s, system)
    return StepResult(
        soc_next=soc_next,
        b=b,
        s=s,
        correction=net - a,
        agent_cost=cost,
        stage_cost=cost.sum(axis=-1),
        grid_power=np.maximum(b.sum(axis=-1), s.sum(axis=-1)),
    )


# -- whole days -----------------------------------------------------------------------------
def discounted_return(stage_costs: Any, gamma: float) -> np.ndarray:
    """Discounted sum over hours, ``sum_k gamma^k c_k``: a day's J (paper eq. 4) of the stage
    costs ``L~``, or J^i (eq. 5) of one battery's.

    Parameters
    ----------
    stage_costs : array_like, shape ``(hours, ...)``
        Costs with the hour first, e.g. ``(hours, days)`` or ``(hours, days, n)``.
    gamma : float
        Discount factor in ``(0, 1]``.

    Returns
    -------
    numpy.ndarray, shape ``stage_costs.shape[1:]``
        E.g. ``(days,)`` or ``(days, n)``.
    """
    costs = _as_float_array("stage_costs", stage_costs)
    if costs.ndim < 1:
        raise ValueError(f"stage_costs has shape {costs.shape}: expected (hours, ...)")
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float, np.floating, np.integer)):
        raise ValueError(f"gamma={gamma!r}: expected a real number in (0, 1]")  # noqa: TRY004
    if not (np.isfinite(gamma) and 0.0 < gamma <= 1.0):
        raise ValueError(f"gamma={gamma!r}: expected a value in (0, 1]")
    weights = float(gamma) ** np.arange(costs.shape[0])
    return np.tensordot(weights, costs, axes=(0, 0))
