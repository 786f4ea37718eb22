r"""The paper's centralized MPC (eq. 9), written once in CasADi.

Decision variables, ordered stage by stage. Stage ``j = 0 .. N-1`` holds the block

.. math:: z_j = (\hat b_j, \hat s_j, \widehat{soc}_{j+1}, \sigma^{hi}_{j+1}, \sigma^{lo}_{j+1})
          \in \mathbb R^{5n},

so ``x = (z_0, ..., z_{N-1})`` has ``5 n N`` entries. The initial state is the parameter
``soc0`` (eq. 9g substituted), and the stage-0 slacks and ``phi_theta(soc0)`` are constants
of the cost (they are included in the reported cost but cannot change the solution).

Parameters ``p = (soc0 (n), buy (N), sell (N), theta (10 n))`` -- see :mod:`mpcrl_lite.theta`.

Cost (eq. 9a with the parametrisation of eqs. 23a-23c)

.. math::
   f = \sum_{j=0}^{N-1}\gamma^j \sum_i \big[(\phi_{b,j}+\theta_b^i)\hat b^i_j
        - (\phi_{s,j}+\theta_s^i)\hat s^i_j + \phi_\theta(\widehat{soc}^i_j)
        + \omega^\top \sigma^i_j\big]
       + \sum_i \big[T_\theta(\widehat{soc}^i_N) + \omega_f^\top\sigma^i_N\big].

Equality constraints ``g(x, p) = 0`` (eq. 9b), ``n`` per stage:
``soc_{j+1} - soc_j - theta_alpha (b_j - s_j) - theta_delta``.

Inequality constraints ``h(x, p) <= 0``, ``8 n + 2`` per stage, in this order:
``-b, b - U, -s, s - U`` (eq. 9e), ``sum b - P, sum s - P`` (eq. 9f),
``soc - 0.9 - sigma_hi, 0.1 - soc - sigma_lo, -sigma_hi, -sigma_lo`` (eqs. 9c-9d);
:data:`INEQUALITIES` names these groups and :meth:`MPC.inequality_index` gives their rows, so
back-ends never write the layout down themselves.

For fixed theta this is a QP in ``x``: ``f = 0.5 x'Hx + q'x + c``, ``g = A x - e``,
``h = C x - d``; :meth:`MPC.qp_data` evaluates that data so every solver back-end consumes
the same formulation. ``H`` is diagonal (only soc carries quadratic costs), ``C`` and ``d``
do not depend on the parameters, and ``A`` depends on theta only.

Every back-end solves the *barrier problem* with the barrier parameter ``tau`` fixed:

.. math:: \min_x f(x,p) - \tau\sum_k \log(-h_k(x,p)) \quad\text{s.t.}\quad g(x,p) = 0,

whose KKT conditions are ``grad f + A' lam + C' mu = 0``, ``g = 0``, ``mu_k h_k = -tau``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .._util.lazy import lazy_module
from ..config import SystemConfig
from ..theta import PARTS, Theta

ca = lazy_module("casadi")  # CasADi (~0.1-0.2 s of import) loads when first used

__all__ = ["GRID_INEQUALITIES", "INEQUALITIES", "MPC", "Plan", "QPData"]

#: The groups of inequality rows of one stage of ``h``, in their order: name -> the constraint
#: ``expression <= 0``. A group has one row per agent, except the grid limits (one row).
INEQUALITIES: dict[str, str] = {
    "b_min": "-b",
    "b_max": "b - U_bar",
    "s_min": "-s",
    "s_max": "s - U_bar",
    "grid_b": "sum_i b - P_bar",
    "grid_s": "sum_i s - P_bar",
    "soc_max": "soc - soc_high - sigma_hi",
    "soc_min": "soc_low - soc - sigma_lo",
    "sigma_hi_min": "-sigma_hi",
    "sigma_lo_min": "-sigma_lo",
}
#: The groups of :data:`INEQUALITIES` with one row per stage (the grid peak limits, eq. 9f).
GRID_INEQUALITIES = ("grid_b", "grid_s")


@dataclass(frozen=True)
class QPData:
    """The MPC's QP for one parameter value (dense numpy arrays).

    ``f = 0.5 x' H x + q' x + c``, ``A x = e``, ``C x <= d``.
    Shapes: H (nx, nx) diagonal, q (nx,), A (neq, nx), e (neq,), C (nin, nx), d (nin,).
    """

    H: np.ndarray
    q: np.ndarray
    c: float
    A: np.ndarray
    e: np.ndarray
    C: np.ndarray
    d: np.ndarray


@dataclass(frozen=True)
class Plan:
    """An MPC solution laid out in time: arrays of shape ``(N, n)`` (``soc``: ``(N+1, n)``,
    row 0 the measured state)."""

    b: np.ndarray
    s: np.ndarray
    soc: np.ndarray
    sigma_hi: np.ndarray
    sigma_lo: np.ndarray

    @property
    def action(self) -> np.ndarray:
        """The planned net power ``b - s``, shape ``(N, n)``; row 0 is the policy."""
        return self.b - self.s


class MPC:
    """The symbolic MPC (paper eq. 9) for one system; build once, reuse for every solve.

    Parameters
    ----------
    system
        Sizes, bounds, weights and the discount factor (:class:`SystemConfig`).
    """

    def __init__(self, system: SystemConfig | None = None) -> None:
        self.system = system or SystemConfig()
        n, N = self.system.n, self.system.N
        self.n, self.N = n, N
        self.nx = 5 * n * N
        self.neq = n * N
        self.nin = (8 * n + 2) * N
        self.n_theta = len(PARTS) * n
        self.np = n + 2 * N + self.n_theta
        # the symbolic problem (CasADi) is built when first used (:meth:`__getattr__`): the
        # compiled back-end solves from closed forms, and a learner is ready without it

    #: what :meth:`build_problem` sets
    _BUILT = frozenset({"_x", "_p", "_f", "_g", "_h", "fgh", "qp_function"})

    def __getattr__(self, name: str):
        # only reached for names not set yet: the symbolic problem's, built on first read
        if name in MPC._BUILT and "fgh" not in self.__dict__:
            self.build_problem()
            return self.__dict__[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    # -- layout ---------------------------------------------------------------------------
    def index(self, name: str, stage: int | None = None) -> np.ndarray:
        """Indices into ``x`` of ``name`` in {'b', 's', 'soc', 'sigma_hi', 'sigma_lo'}.

        Without ``stage``: shape ``(N, n)``; with it: ``(n,)``. ``soc``/``sigma`` at stage
        ``j`` are the values at prediction step ``j + 1``.
        """
        names = ("b", "s", "soc", "sigma_hi", "sigma_lo")
        if name not in names:
            raise ValueError(f"unknown variable {name!r}; expected one of {names}")
        n = self.n
        k = names.index(name)
        idx = (np.arange(self.N)[:, None] * 5 * n) + k * n + np.arange(n)[None, :]
        return idx if stage is None else idx[stage]

    def inequality_index(self, name: str, stage: int | None = None) -> np.ndarray:
        """Rows of ``h`` of the inequality group ``name`` (a key of :data:`INEQUALITIES`).

        Groups with a row per agent: shape ``(N, n)``, with ``stage`` ``(n,)``; the grid
        groups (:data:`GRID_INEQUALITIES`): ``(N,)``, with ``stage`` a 0-d array. Rows at
        stage ``j`` constrain the inputs of stage ``j`` and soc/sigma at step ``j + 1``.
        """
        if name not in INEQUALITIES:
            raise ValueError(
                f"unknown inequality group {name!r}; expected one of {tuple(INEQUALITIES)}"
            )
        sizes = [1 if group in GRID_INEQUALITIES else self.n for group in INEQUALITIES]
        k = list(INEQUALITIES).index(name)
        start = sum(sizes[:k])
        rows = np.arange(self.N)[:, None] * sum(sizes) + start + np.arange(sizes[k])[None, :]
        if name in GRID_INEQUALITIES:
            rows = rows[:, 0]
        return rows if stage is None else rows[stage]

    @cached_property
    def policy_selector(self) -> np.ndarray:
        """Matrix ``S`` of shape ``(n, nx)`` with ``pi = S x = b_0 - s_0``: the policy
        (paper eqs. 10, 11) is the first input ``u_0`` (eq. 21) of the plan."""
        S = np.zeros((self.n, self.nx))
        S[np.arange(self.n), self.index("b", 0)] = 1.0
        S[np.arange(self.n), self.index("s", 0)] = -1.0
        return S

    def parameters(
        self, soc0: np.ndarray, buy: np.ndarray, sell: np.ndarray, theta: Theta | np.ndarray
    ) -> np.ndarray:
        """Stack ``(soc0, buy, sell, theta)`` into ``p``; leading batch axes are kept.

        soc0 (..., n), buy and sell (..., N), theta a :class:`Theta`, an (n_theta,) vector or
        one vector per problem, (..., n_theta) with the batch axes of the others (runs
        stacked in lockstep). Returns (..., np).
        """
        soc0 = np.asarray(soc0, dtype=float)
        buy = np.asarray(buy, dtype=float)
        sell = np.asarray(sell, dtype=float)
        tvec = theta.to_vector() if isinstance(theta, Theta) else np.asarray(theta, float)
        if soc0.shape[-1:] != (self.n,):
            raise ValueError(f"soc0 has shape {soc0.shape}; expected (..., n={self.n})")
        if buy.shape[-1:] != (self.N,) or sell.shape[-1:] != (self.N,):
            raise ValueError(
                f"price windows have shapes {buy.shape}, {sell.shape}; expected (..., N={self.N})"
            )
        lead = soc0.shape[:-1]
        if buy.shape[:-1] == lead and sell.shape[:-1] == lead:
            batch = lead  # the usual call (one hour of a month): nothing to broadcast
        else:
            batch = np.broadcast_shapes(lead, buy.shape[:-1], sell.shape[:-1])
        if tvec.shape[-1:] != (self.n_theta,) or (tvec.ndim > 1 and tvec.shape[:-1] != batch):
            raise ValueError(f"theta has shape {tvec.shape}; expected ({self.n_theta},) or one "
                             f"per problem, {batch + (self.n_theta,)}")
        n, N = self.n, self.N
        p = np.empty(batch + (self.np,))
        p[..., :n] = soc0
        p[..., n:n + N] = buy
        p[..., n + N:n + 2 * N] = sell
        p[..., n + 2 * N:] = tvec
        if not np.isfinite(p).all():
            raise ValueError("MPC parameters contain non-finite values (soc0, prices or theta)")
        return p

    def plan(self, x: np.ndarray, soc0: np.ndarray) -> Plan:
        """Lay a primal solution ``x`` (nx,) out in time."""
        x = np.asarray(x, dtype=float)
        soc = np.vstack([np.asarray(soc0, float)[None, :], x[self.index("soc")]])
        return Plan(
            b=x[self.index("b")],
            s=x[self.index("s")],
            soc=soc,
            sigma_hi=x[self.index("sigma_hi")],
            sigma_lo=x[self.index("sigma_lo")],
        )

    # -- symbolic formulation -------------------------------------------------------------
    def build_problem(self) -> None:
        r"""Build the paper's MPC (eq. 9) symbolically: the cost 9a with the parametrised costs
        of eqs. 23a-23c, the model 9b, the relaxed soc band 9c-9d, the input bounds 9e, the
        grid peak limits 9f (eq. 7 for the plan) and the initial state 9g (substituted), in the
        layout of the module docstring; then the CasADi Functions :attr:`fgh` and
        :attr:`qp_function` every back-end uses. Called once, on the first read of one of
        them (a :class:`MPC` is cheap to make: the compiled back-end needs none of them)."""
        sysc, n, N = self.system, self.n, self.N
        x = ca.SX.sym("x", self.nx)
        p = ca.SX.sym("p", self.np)
        soc0 = p[:n]
        buy = p[n : n + N]
        sell = p[n + N : n + 2 * N]
        th = {name: p[n + 2 * N + i * n : n + 2 * N + (i + 1) * n] for i, name in enumerate(PARTS)}

        def var(name: str, j: int) -> ca.SX:
            idx = self.index(name, j)
            return x[int(idx[0]) : int(idx[-1]) + 1]

        w_hi, w_lo = sysc.omega
        wf_hi, wf_lo = sysc.omega_f
        lo, hi = sysc.soc_low, sysc.soc_high

        def phi(soc: ca.SX) -> ca.SX:
            return ca.sum1(th["phi1"] * soc**2 + th["phi2"] * soc + th["phi3"])

        # constant stage-0 terms: phi_theta(soc0) and the slack that soc0 forces
        cost = phi(soc0) + ca.sum1(w_hi * ca.fmax(soc0 - hi, 0) + w_lo * ca.fmax(lo - soc0, 0))
        g, h = [], []
        U_bar = sysc.U_bar  # one bound for all batteries, or each battery's own
        U_bar = U_bar if isinstance(U_bar, float) else ca.DM(list(U_bar))
        soc_prev = soc0
        for j in range(N):
            b, s = var("b", j), var("s", j)
            soc, shi, slo = var("soc", j), var("sigma_hi", j), var("sigma_lo", j)
            disc = sysc.gamma**j
            cost += disc * ca.sum1((buy[j] + th["b"]) * b - (sell[j] + th["s"]) * s)
            if j + 1 < N:
                cost += sysc.gamma ** (j + 1) * (phi(soc) + ca.sum1(w_hi * shi + w_lo * slo))
            else:
                cost += ca.sum1(th["T1"] * soc**2 + th["T2"] * soc + th["T3"])
                cost += ca.sum1(wf_hi * shi + wf_lo * slo)
            g.append(soc - soc_prev - th["alpha"] * (b - s) - th["delta"])
            h += [  # the groups of INEQUALITIES, in its order
                -b,
                b - U_bar,
                -s,
                s - U_bar,
                ca.sum1(b) - sysc.P_bar,
                ca.sum1(s) - sysc.P_bar,
                soc - hi - shi,
                lo - soc - slo,
                -shi,
                -slo,
            ]
            soc_prev = soc
        g_expr = ca.vertcat(*g)
        h_expr = ca.vertcat(*h)
        self._x, self._p = x, p
        self._f, self._g, self._h = cost, g_expr, h_expr

        #: f, g, h at (x, p)
        self.fgh = ca.Function("mpc_fgh", [x, p], [cost, g_expr, h_expr], ["x", "p"], ["f", "g", "h"])
        # QP data: exact because f is quadratic and g, h are affine in x
        H = ca.hessian(cost, x)[0]
        q = ca.substitute(ca.gradient(cost, x), x, ca.DM.zeros(self.nx))
        c = ca.substitute(cost, x, ca.DM.zeros(self.nx))
        A = ca.jacobian(g_expr, x)
        e = -ca.substitute(g_expr, x, ca.DM.zeros(self.nx))
        C = ca.jacobian(h_expr, x)
        d = -ca.substitute(h_expr, x, ca.DM.zeros(self.nx))
        #: QP data of the MPC at p: H, q, c, A, e, C, d
        self.qp_function = ca.Function(
            "mpc_qp", [p], [H, q, c, A, e, C, d], ["p"], ["H", "q", "c", "A", "e", "C", "d"]
        )

    # -- numeric helpers ------------------------------------------------------------------
    def shift(self, x: np.ndarray) -> np.ndarray:
        """Warm start for the next hour: drop stage 0, repeat the last stage.

        ``x`` has shape ``(..., nx)``; the result has the same shape. Every back-end and the
        closed loop warm start through this one method.
        """
        x = np.asarray(x, dtype=float)
        if x.shape[-1:] != (self.nx,):
            raise ValueError(f"x has shape {x.shape}; expected (..., nx={self.nx})")
        stage = 5 * self.n
        out = np.empty_like(x)
        out[..., :-stage] = x[..., stage:]
        out[..., -stage:] = x[..., -stage:]
        return out

    def qp_data(self, p: np.ndarray) -> QPData:
        """The QP at one parameter vector ``p`` of shape ``(np,)``."""
        H, q, c, A, e, C, d = self.qp_function(np.asarray(p, float))
        return QPData(
            H=np.array(H),
            q=np.array(q).ravel(),
            c=float(c),
            A=np.array(A),
            e=np.array(e).ravel(),
            C=np.array(C),
            d=np.array(d).ravel(),
        )

    def evaluate(self, x: np.ndarray, p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """``(f, g, h)`` at one ``x`` (nx,) and ``p`` (np,)."""
        f, g, h = self.fgh(np.asarray(x, float), np.asarray(p, float))
        return float(f), np.array(g).ravel(), np.array(h).ravel()

    @property
    def symbols(self) -> tuple[ca.SX, ca.SX, ca.SX, ca.SX, ca.SX]:
        """``(x, p, f, g, h)`` as CasADi SX, for back-ends and the sensitivity module."""
        return self._x, self._p, self._f, self._g, self._h

    @property
    def theta_slice(self) -> slice:
        """Where theta sits inside ``p``."""
        start = self.n + 2 * self.N
        return slice(start, start + self.n_theta)

    # -- the barrier problem's KKT conditions ---------------------------------------------
    @cached_property
    def kkt(self) -> KKT:
        """The KKT residual of the barrier problem and its Jacobians (built on first use)."""
        return KKT(self)


class KKT:
    r"""KKT conditions of the barrier problem (paper eqs. 18, 19), as CasADi Functions.

    With ``y = (x, lam, mu)`` of size ``ny = nx + neq + nin``:

    .. math:: R(y, p; \tau) = \begin{bmatrix} \nabla_x f + \nabla_x g\,\lambda
              + \nabla_x h\,\mu \\ g \\ \mu \circ h + \tau \end{bmatrix} = 0 .

    ``jacobians(y, p, tau)`` returns ``dR/dy`` (sparse, ``ny x ny``) and ``dR/dtheta``
    (``ny x n_theta``); ``newton(y, p, tau)`` returns the Newton step ``-dR/dy^{-1} R``.
    """

    def __init__(self, mpc: MPC) -> None:
        x, p, f, g, h = mpc.symbols
        lam = ca.SX.sym("lam", mpc.neq)
        mu = ca.SX.sym("mu", mpc.nin)
        tau = ca.SX.sym("tau")
        y = ca.vertcat(x, lam, mu)
        lagrangian = f + ca.dot(lam, g) + ca.dot(mu, h)
        R = ca.vertcat(ca.gradient(lagrangian, x), g, mu * h + tau)
        theta = p[mpc.theta_slice]
        self.mpc = mpc
        self.ny = mpc.nx + mpc.neq + mpc.nin
        self.residual = ca.Function("kkt_residual", [y, p, tau], [R], ["y", "p", "tau"], ["R"])
        K = ca.jacobian(R, y)
        R_theta = ca.jacobian(R, theta)
        self.jacobians = ca.Function(
            "kkt_jacobians", [y, p, tau], [K, R_theta], ["y", "p", "tau"], ["K", "R_theta"]
        )
        # Newton step with CasADi's sparse QR (fast for the sizes of this problem)
        ym, pm, taum = ca.MX.sym("y", self.ny), ca.MX.sym("p", mpc.np), ca.MX.sym("tau")
        Km, _ = self.jacobians(ym, pm, taum)
        Rm = self.residual(ym, pm, taum)
        self.newton = ca.Function(
            "kkt_newton", [ym, pm, taum], [-ca.solve(Km, Rm, "qr")], ["y", "p", "tau"], ["dy"]
        )

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x, lam, mu)`` from ``y``."""
        m = self.mpc
        return y[: m.nx], y[m.nx : m.nx + m.neq], y[m.nx + m.neq :]
