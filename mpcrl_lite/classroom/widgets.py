r"""Interactive explorers for the notebooks, built from ipywidgets.

Every builder returns an :class:`Explorer` (an :class:`ipywidgets.VBox`) that can be displayed
in a notebook and driven from code, so it is testable without a running kernel:

* ``explorer.controls`` -- ``{name: widget}``; set ``explorer.controls['P_bar'].value = 1.0``
  and the explorer recomputes (synchronously) as if the slider had been released;
* ``explorer.values`` -- the controls' values; a day is the package's day index (0 = the
  first day) while its slider shows days from 1;
* ``explorer.result`` -- the data of the latest update (a :class:`~mpcrl_lite.sim.record.Record`
  or a dict of arrays from :mod:`mpcrl_lite.classroom.explorers`);
* ``explorer.figure`` -- the :class:`matplotlib.figure.Figure` it drew (by
  :mod:`mpcrl_lite.figures.plots`), shown through ``explorer.image``: a PNG drawn at
  :attr:`Explorer.dpi` = 150 and shown at 100 CSS pixels per inch of the figure, never wider;
* ``explorer.last_update_s`` -- the wall time of the latest update (simulation + drawing).

The controls come from :mod:`mpcrl_lite.classroom.controls`: every one has an accessible name and a
tooltip; sliders run from small (left) to large (right) values and send their value when
released, so an MPC is solved on release, never while a slider is dragged. Figures are plain
:class:`~matplotlib.figure.Figure` objects (not pyplot), so nothing is displayed twice by the
inline backend.

How the MPC is solved comes from :class:`~mpcrl_lite.config.MPCConfig` (default
``MPCConfig()``, ``tau = 0.1``); ``tau`` and ``backend`` arguments override single fields.

============================  =============================================================
builder                       what it shows
============================  =============================================================
:func:`price_day_picker`      the prices of a day and the MPC's forecast window at an hour
:func:`rule_explorer`         one day of the true system under a price-threshold rule
:func:`day_explorer`          one day of the MPC in closed loop (P_bar, noise, prices, tau, N)
:func:`tau_explorer`          the MPC policy as a function of one input, for a barrier tau
:func:`lstd_explorer`         LSTD value fits of a recorded month against Monte-Carlo returns
============================  =============================================================

The data helpers (:func:`threshold_rule`, :func:`simulate_day`, :func:`policy_curve`,
:func:`value_fit`, :func:`cached_solver`, ...) live in :mod:`mpcrl_lite.classroom.explorers` and the
drawing in :mod:`mpcrl_lite.figures.plots`; their names stay importable from here.
"""

from __future__ import annotations

import html
import io
import math
import re
import time
from collections.abc import Sequence
from typing import Any

import ipywidgets as widgets
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..config import HOURS_PER_DAY, PRICE_UNIT, VALUE_FEATURE_SETS, MPCConfig, SystemConfig
from ..figures.describe import describe_figure
from ..figures.plots import (
    plot_day,
    plot_policy_curve,
    plot_price_window,
    plot_value_fit,
)
from ..figures.style import COST_UNIT
from ..sim.record import MonthRecord, Record
from ..system.prices import Prices
from ..theta import Theta
from .controls import (
    choice_slider,
    day_slider,
    dropdown,
    float_slider,
    int_box,
    int_slider,
    log_slider,
)
from .explorers import (
    POLICY_RANGES,
    POLICY_VARIABLES,
    TAUS,
    policy_curve,
    price_window,
    replace_system,
    resolve_mpc_config,
    rule_day,
    simulate_day,
    value_fit,
)
from .picture import Picture

# The data helpers and figure-first drawing functions lived here before; their names stay.
__all__ = ["DayExplorer", "Explorer", "LSTDExplorer", "PriceDayPicker", "RuleExplorer", "TauExplorer", "day_explorer", "lstd_explorer", "price_day_picker", "rule_explorer", "tau_explorer"]


def _layout_signature(fig: Figure) -> tuple:
    """What a constrained layout depends on, read without drawing: per axes its labels,
    whether it has a title (a left-aligned title only takes height), its legend texts and
    the widest y tick label."""
    signature = []
    for ax in fig.axes:
        yaxis = ax.yaxis
        ticks = yaxis.get_major_formatter().format_ticks(yaxis.get_majorticklocs())
        legend = ax.get_legend()
        texts = tuple(t.get_text() for t in legend.get_texts()) if legend else ()
        signature.append((ax.get_ylabel(), ax.get_xlabel(), bool(ax.get_title("left")), texts,
                          max((len(t) for t in ticks), default=0)))
    return tuple(signature)


class Explorer(widgets.VBox):
    """Controls on top, a status line, then the figure (as a PNG image).

    Subclasses implement :meth:`compute` (returns the new ``result``) and :meth:`draw`.
    Changing any control's value calls :meth:`update`; an error is shown in the status line
    and kept in ``error`` (the widget stays usable).
    """

    #: Resolution of the PNG, in pixels per inch of the figure.
    dpi = 150
    #: Displayed size: CSS pixels per inch of the figure (the image is never shown wider).
    css_px_per_inch = 100

    def __init__(self, controls: dict[str, widgets.Widget], figsize: tuple[float, float],
                 columns: int = 2, render: bool = True) -> None:
        self.controls = controls
        self.figure = Figure(figsize=figsize, dpi=self.dpi, layout="constrained")
        # one canvas (and renderer) for all updates: its text metrics stay cached
        FigureCanvasAgg(self.figure)
        self._layout: tuple[tuple, list] | None = None
        self.image = Picture(
            format="png", width=str(round(figsize[0] * self.css_px_per_inch)),
            layout=widgets.Layout(max_width="100%", height="auto", align_self="flex-start"),
        )
        self.status = widgets.HTML(tooltip="")
        self.render = render
        self.result: Any = None
        self.error: Exception | None = None
        self.last_update_s = float("nan")
        self.updates = 0
        rows = [
            widgets.HBox(list(controls.values())[i : i + columns],
                         layout=widgets.Layout(flex_flow="row wrap"))
            for i in range(0, len(controls), columns)
        ]
        super().__init__(children=[*rows, self.status, self.image])
        for control in controls.values():
            control.observe(self._on_change, names="value")
        self.update()

    def _on_change(self, _change: dict) -> None:
        self.update(raise_errors=False)

    @property
    def values(self) -> dict[str, Any]:
        """Current value of every control."""
        return {name: control.value for name, control in self.controls.items()}

    def compute(self) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def draw(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:
        """One line of HTML about the latest result."""
        return ""

    def alt_text(self) -> str:
        """What the figure shows, in words (:func:`~mpcrl_lite.figures.describe.describe_figure`:
        title, panels, series, data ranges), then the status line's numbers."""
        summary = html.unescape(re.sub(r"<[^>]+>", "", self.describe())).strip()
        return f"{describe_figure(self.figure)} {summary}".strip()

    def _png(self) -> bytes:
        """The figure as PNG. The constrained layout (about half the drawing time) is
        computed again only when the texts that set the margins have changed; otherwise the
        axes keep the positions of the last layout."""
        fig = self.figure
        signature = _layout_signature(fig)
        reuse = self._layout is not None and self._layout[0] == signature
        if reuse:
            fig.set_layout_engine(None)  # not "none": that still runs a dry draw
            for ax, box in zip(fig.axes, self._layout[1]):  # type: ignore[index]
                ax.set_position(box)
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=self.dpi)
        if not reuse:
            self._layout = (signature, [ax.get_position() for ax in fig.axes])
        return buffer.getvalue()

    def update(self, raise_errors: bool = True) -> None:
        """Recompute with the current control values and redraw."""
        t0 = time.perf_counter()
        self.status.value = "<i>computing…</i>"
        try:
            self.result = self.compute()
        except Exception as err:  # any failure is shown; the widget lives on
            self.error = err
            self.status.value = (f"<span role='status'><b style='color:#b00'>error:</b> "
                                 f"{html.escape(str(err))}</span>")
            if raise_errors:
                raise
            return
        self.error = None
        self.draw()
        if self.render:
            self.image.value = self._png()
            self.image.alt = self.alt_text()
        self.updates += 1
        self.last_update_s = time.perf_counter() - t0
        self.status.value = (f"<span role='status'>{self.describe()} "
                             f"<small>({self.last_update_s:.2f} s)</small></span>")


# -- controls shared by several explorers ---------------------------------------------------
def _p_bar_slider(system: SystemConfig) -> widgets.Widget:
    # at P_bar >= n U_bar the grid limit can no longer bind
    top = round(max(system.n * system.U_bar, system.P_bar), 1)
    return float_slider("P̄ grid limit (MW)", system.P_bar, 0.1, top, 0.1, ".1f",
                        "grid limit P bar in megawatts",
                        "Largest total power the batteries may buy or sell together (P_bar)")


def _noise_slider(system: SystemConfig) -> widgets.Widget:
    return float_slider("noise variance (MW²)", system.noise_var, 0.0, 1.5, 0.05, ".2f",
                        "noise variance in megawatts squared",
                        "Variance of the production-demand noise Delta; one seed gives the "
                        "same draws, scaled")


def _tau_slider(value: float, taus: Sequence[float]) -> widgets.Widget:
    return log_slider("barrier τ", value, taus, "barrier parameter tau",
                      "Barrier parameter of the MPC: small (left) is nearly the exact, "
                      "bang-bang MPC; large (right) smooths the policy")


def _hour_slider(value: int) -> widgets.Widget:
    return int_slider("hour k", value, 0, HOURS_PER_DAY - 1, "hour of the day",
                      "Hour of the day at which the MPC looks ahead",
                      [f"{k:02d}:00" for k in range(HOURS_PER_DAY)])


def _seed_box(value: int) -> widgets.Widget:
    return int_box("noise seed", value, 0, 10**6,
                   "Seed of the noise: the same seed gives the same noise draws")


def _days(prices: Prices | None, system: SystemConfig) -> int:
    return (Prices.default(system) if prices is None else prices).days


# -- explorers ------------------------------------------------------------------------------
class PriceDayPicker(Explorer):
    """Prices of one day and the MPC's forecast window (see :func:`price_day_picker`)."""

    def __init__(self, prices: Prices, day: int, hour: int, N: int, render: bool) -> None:
        self.prices = prices
        controls = {
            "day": day_slider(day, prices.days),
            "hour": _hour_slider(hour),
            "N": int_slider("horizon N (h)", N, 1, HOURS_PER_DAY, "prediction horizon N in hours",
                            "Number of hours the MPC's forecast window covers"),
        }
        super().__init__(controls, figsize=(8.5, 3.4), columns=3, render=render)

    def compute(self) -> dict[str, np.ndarray]:
        v = self.values
        return price_window(self.prices, v["day"], v["hour"], v["N"])

    def draw(self) -> None:
        v = self.values
        plot_price_window(self.prices, v["day"], v["hour"], v["N"], fig=self.figure)

    def describe(self) -> str:
        buy = self.result["buy"]
        return (f"window: {buy.size} prices, buy from {buy.min():.1f} to {buy.max():.1f} "
                f"{self.prices.unit}")


class RuleExplorer(Explorer):
    """One day under :func:`threshold_rule` (see :func:`rule_explorer`)."""

    def __init__(self, system: SystemConfig, prices: Prices | None, day: int, seed: int,
                 buy_below: float, sell_above: float, soc_min: float, soc_max: float,
                 render: bool) -> None:
        self.system = system
        self.prices = prices
        controls = {
            "buy_below": float_slider(f"buy below ({PRICE_UNIT})", buy_below, 0.0, 130.0, 1.0,
                                      ".0f", "buy below this price, NOK per megawatt hour",
                                      "Charge at full power when the price is at most this"),
            "sell_above": float_slider(f"sell above ({PRICE_UNIT})", sell_above, 0.0, 130.0,
                                       1.0, ".0f", "sell above this price, NOK per megawatt hour",
                                       "Discharge at full power when the price is at least this"),
            "soc_min": float_slider("stop selling at soc", soc_min, 0.0, 1.0, 0.05, ".2f",
                                    tooltip="No discharging below this state of charge"),
            "soc_max": float_slider("stop buying at soc", soc_max, 0.0, 1.0, 0.05, ".2f",
                                    tooltip="No charging above this state of charge"),
            "noise_var": _noise_slider(system),
            "day": day_slider(day, _days(prices, system)),
            "seed": _seed_box(seed),
        }
        super().__init__(controls, figsize=(8.5, 8.0), columns=2, render=render)

    def compute(self) -> Record:
        v = self.values
        system = replace_system(self.system, noise_var=float(v["noise_var"]))
        return rule_day(system, v["day"], v["seed"], v["buy_below"], v["sell_above"],
                        v["soc_min"], v["soc_max"], self.prices)

    def draw(self) -> None:
        t = self.result
        title = (f"Rule, day {self.values['day'] + 1}: J = {t.J():.1f} {COST_UNIT}, "
                 f"{t.hours_soc_below()} agent-hours below soc 0.1")
        plot_day(t, 0, fig=self.figure, title=title, planned=False)

    def describe(self) -> str:
        t = self.result
        return (f"J = {t.J():.1f} {COST_UNIT}; agent-hours soc &lt; 0.1: {t.hours_soc_below()}, "
                f"&gt; 0.9: {t.hours_soc_above()}; low-level interventions: "
                f"{int(np.count_nonzero(np.abs(t.correction) > 1e-12))}")


class DayExplorer(Explorer):
    """One day of the MPC in closed loop (see :func:`day_explorer`)."""

    def __init__(self, system: SystemConfig, theta: Theta | dict[str, Theta] | None,
                 prices: Prices | None, day: int, seed: int, mpc_config: MPCConfig,
                 render: bool) -> None:
        self.system = system
        self.thetas = theta if isinstance(theta, dict) else None
        self.theta = None if isinstance(theta, dict) else theta
        self.prices = prices
        self.mpc_config = mpc_config
        controls = {
            "P_bar": _p_bar_slider(system),
            "noise_var": _noise_slider(system),
            "price_scale": float_slider("price scale", system.price_scale, 0.25, 4.0, 0.25,
                                        ".2f", tooltip="Factor on every price of the month"),
            "tau": _tau_slider(mpc_config.tau, TAUS),
            "N": int_slider("horizon N (h)", system.N, 1, 24, "prediction horizon N in hours",
                            "Number of hours the MPC plans ahead"),
            "day": day_slider(day, _days(prices, system)),
            "seed": _seed_box(seed),
        }
        if self.thetas is not None:
            if not self.thetas:
                raise ValueError("theta: expected a Theta or a non-empty {name: Theta} dict")
            controls["theta"] = dropdown("MPC parameters θ", list(self.thetas),
                                         next(iter(self.thetas)),
                                         "Which MPC parameters run the day (same noise)")
        super().__init__(controls, figsize=(8.5, 8.0), columns=2, render=render)

    def current_theta(self, system: SystemConfig) -> Theta:
        """The MPC parameters in use: the chosen one, the given one or theta0."""
        if self.thetas is not None:
            return self.thetas[self.values["theta"]]
        return self.theta if self.theta is not None else Theta.nominal(system)

    def current_system(self) -> SystemConfig:
        """The system with the controls' values."""
        v = self.values
        return replace_system(self.system, P_bar=float(v["P_bar"]),
                              noise_var=float(v["noise_var"]),
                              price_scale=float(v["price_scale"]), N=int(v["N"]))

    def compute(self) -> MonthRecord:
        v = self.values
        system = self.current_system()
        month = Prices.default(system) if self.prices is None else self.prices.scaled(
            float(v["price_scale"]))
        return simulate_day(system, v["day"], v["seed"], self.current_theta(system),
                            prices=month, mpc_config=self.mpc_config.replace(tau=v["tau"]))

    @property
    def summary(self) -> dict[str, Any]:
        """``result.summary()`` of the latest day."""
        return self.result.summary()

    def draw(self) -> None:
        s = self.result.summary()
        title = (f"MPC, day {self.values['day'] + 1}: J = {s['J']:.1f} {COST_UNIT}, "
                 f"max planned P = {s['max_P_mpc']:.2f} MW")
        plot_day(self.result, 0, fig=self.figure, title=title)

    def describe(self) -> str:
        s = self.result.summary()
        return (f"J = {s['J']:.1f} {COST_UNIT}; agent-hours soc &lt; 0.1: "
                f"{s['hours_soc_below_0_1']}; max planned P = {s['max_P_mpc']:.2f} MW, "
                f"applied {s['max_P_applied']:.2f} MW; solver failures: {s['solver_failures']}")


class TauExplorer(Explorer):
    """The MPC policy versus one input, for a chosen barrier parameter (see
    :func:`tau_explorer`)."""

    def __init__(self, system: SystemConfig, theta: Theta | None, variable: str,
                 taus: Sequence[float], mpc_config: MPCConfig, points: int, hour: int,
                 day: int, render: bool) -> None:
        self.system = system
        self.theta = theta
        self.points = int(points)
        self.mpc_config = mpc_config
        self.taus = tuple(sorted({float(t) for t in taus} | {mpc_config.tau}))
        self.reference: dict[str, Any] | None = None
        self._reference_key: tuple | None = None
        controls = {
            "tau": _tau_slider(mpc_config.tau, self.taus),
            "variable": dropdown("vary", list(POLICY_VARIABLES), variable,
                                 "The input of the policy that is swept"),
            "hour": _hour_slider(hour),
            "day": day_slider(day, _days(None, system)),
            "P_bar": _p_bar_slider(system),
        }
        super().__init__(controls, figsize=(8.0, 5.6), columns=3, render=render)

    def _curve(self, tau: float) -> dict[str, Any]:
        v = self.values
        system = replace_system(self.system, P_bar=float(v["P_bar"]))
        values = np.linspace(*POLICY_RANGES[v["variable"]], self.points)
        return policy_curve(v["variable"], values, system=system, theta=self.theta,
                            hour=v["hour"], day=v["day"],
                            mpc_config=self.mpc_config.replace(tau=tau))

    def compute(self) -> dict[str, Any]:
        v = self.values
        key = (v["variable"], v["hour"], v["day"], v["P_bar"])
        smallest = self.taus[0]
        if self._reference_key != key:
            self.reference = self._curve(smallest)
            self._reference_key = key
        if math.isclose(float(v["tau"]), smallest):
            return self.reference  # type: ignore[return-value]
        return self._curve(float(v["tau"]))

    def draw(self) -> None:
        ref = self.reference if self.result is not self.reference else None
        plot_policy_curve(self.result, ref, fig=self.figure)

    def describe(self) -> str:
        c = self.result
        slope = np.nanmax(np.abs(np.gradient(c["policy"][:, 0], c["x"])))
        return (f"τ = {c['tau']:.0e}: steepest slope of π<sup>1</sup> = {slope:.3g} per unit; "
                f"failed solves: {int(np.count_nonzero(~c['success']))}")


class LSTDExplorer(Explorer):
    """LSTD value fits of a recorded month (see :func:`lstd_explorer`)."""

    def __init__(self, record: Record, features: str, render: bool) -> None:
        self.record = record
        D = record.stage_cost.shape[1]
        controls = {
            "features": dropdown("features", list(VALUE_FEATURE_SETS), features,
                                 "Features of the value function: "
                                 + "; ".join(f"{k}: {d}" for k, d in VALUE_FEATURE_SETS.items())),
            "days": int_slider("days used", D, 1, D, "number of recorded days used",
                               "How many of the recorded days the fit uses"),
            "gamma": choice_slider("discount γ", record.system.gamma, [0.9, 0.95, 0.99, 1.0],
                                   "discount factor gamma", "Discount factor of the returns"),
        }
        super().__init__(controls, figsize=(9.0, 3.8), columns=3, render=render)

    def compute(self) -> dict[str, Any]:
        v = self.values
        return value_fit(self.record, v["features"], v["days"], v["gamma"])

    def draw(self) -> None:
        plot_value_fit(self.result, fig=self.figure)

    def describe(self) -> str:
        r = self.result
        return (f"RMSE of V against the returns: {r['rmse']:.1f} NOK, R<sup>2</sup> = "
                f"{r['r2']:.3f}; condition of the LSTD matrix {r['fit'].condition:.2g}")


# -- builders -------------------------------------------------------------------------------
def price_day_picker(prices: Prices | None = None, day: int = 0, hour: int = 18, N: int = 12,
                     render: bool = True) -> PriceDayPicker:
    """Pick a day and an hour; see the day's prices and what the MPC forecasts from there.

    Controls: ``day`` (index from 0, shown from 1), ``hour``, ``N``. ``result`` =
    ``{'buy': (N,), 'sell': (N,)}``, the window the MPC sees at that hour (reading on into
    the next day after midnight).
    """
    prices = Prices.default() if prices is None else prices
    return PriceDayPicker(prices, day, hour, N, render)


def rule_explorer(system: SystemConfig | None = None, prices: Prices | None = None,
                  day: int = 0, seed: int = 0, buy_below: float = 20.0,
                  sell_above: float = 60.0, soc_min: float = 0.3, soc_max: float = 0.7,
                  render: bool = True) -> RuleExplorer:
    """One day of the true system under :func:`threshold_rule`.

    Controls: ``buy_below``, ``sell_above`` (NOK/MWh), ``soc_min``, ``soc_max``,
    ``noise_var``, ``day`` (index from 0, shown from 1), ``seed``.
    ``result`` is the :class:`~mpcrl_lite.sim.record.Record` of the day.
    """
    system = SystemConfig() if system is None else system
    return RuleExplorer(system, prices, day, seed, buy_below, sell_above, soc_min, soc_max,
                        render)


def day_explorer(system: SystemConfig | None = None,
                 theta: Theta | dict[str, Theta] | None = None,
                 prices: Prices | None = None, day: int = 0, seed: int = 0,
                 tau: float | None = None, backend: str | None = None, render: bool = True,
                 *, mpc_config: MPCConfig | None = None) -> DayExplorer:
    """One day of the MPC in closed loop, re-solved when a slider is released.

    Controls: ``P_bar``, ``noise_var``, ``price_scale``, ``tau``, ``N``, ``day``, ``seed``
    (and ``theta`` when several are given). ``result`` is the day's
    :class:`~mpcrl_lite.learning.history.MonthRecord` (``D = 1``), so
    ``explorer.result.summary()['max_P_mpc'] <= controls['P_bar'].value`` can be checked.
    The noise depends on ``seed`` only, so two settings are compared on the same draws.

    Parameters
    ----------
    system : SystemConfig, optional
        Starting values (default ``SystemConfig()``).
    theta : Theta or dict of Theta, optional
        MPC parameters (default theta0 of the current system), e.g. a learned
        ``history.final_theta()``; a dict ``{name: Theta}`` adds a ``theta`` drop-down to
        switch between them on the same noise.
    prices : Prices, optional
        The month (default the shipped one; ``price_scale`` multiplies it).
    day, seed : int
        Starting values (``day`` is an index from 0; the slider shows days from 1).
    tau, backend : optional
        Override ``mpc_config.tau`` (the slider's start) and ``mpc_config.backend``.
    render : bool
        Draw the PNG (set False to compute only).
    mpc_config : MPCConfig, optional
        How the MPC is solved (default ``MPCConfig()``).
    """
    system = SystemConfig() if system is None else system
    config = resolve_mpc_config(mpc_config, tau, backend)
    return DayExplorer(system, theta, prices, day, seed, config, render)


def tau_explorer(system: SystemConfig | None = None, theta: Theta | None = None,
                 variable: str = "theta_s", taus: Sequence[float] = TAUS,
                 tau: float | None = None, points: int = 41, hour: int = 0, day: int = 0,
                 backend: str | None = None, render: bool = True, *,
                 mpc_config: MPCConfig | None = None) -> TauExplorer:
    """The MPC policy of agent 1 as a function of one input, for a barrier parameter ``tau``.

    The chosen ``tau`` (default ``mpc_config.tau``, i.e. ``MPCConfig().tau``) is drawn solid,
    the smallest of ``taus`` dashed as the nearly exact reference. Controls: ``tau`` (left to
    right: increasing), ``variable`` (see :data:`POLICY_VARIABLES`), ``hour``, ``day``,
    ``P_bar``. ``result`` is a :func:`policy_curve` dict.
    """
    if variable not in POLICY_VARIABLES:
        raise ValueError(f"variable={variable!r}: expected one of {list(POLICY_VARIABLES)}")
    system = SystemConfig() if system is None else system
    config = resolve_mpc_config(mpc_config, tau, backend)
    return TauExplorer(system, theta, variable, taus, config, points, hour, day, render)


def lstd_explorer(record: Record, features: str = "paper", render: bool = True
                  ) -> LSTDExplorer:
    """Fit the value of the policy behind ``record`` by LSTD and compare it with the
    Monte-Carlo returns; no MPC is solved, so updates are instant.

    Controls: ``features`` (see :data:`VALUE_FEATURE_SETS`), ``days`` (how many of the recorded days
    are used), ``gamma``. ``result`` is a :func:`value_fit` dict.
    """
    if features not in VALUE_FEATURE_SETS:
        raise ValueError(f"features={features!r}: expected one of {list(VALUE_FEATURE_SETS)}")
    return LSTDExplorer(record, features, render)
