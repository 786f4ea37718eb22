r"""Q-learning against the reference library: ``mpcrl`` 1.4.1's ``LstdQLearningAgent``.

The same MPC, the same transitions and the same settings on both sides; the first and the
second update of theta must agree within 1e-6 relative (``--check`` exits 1 otherwise).

The same problem on both sides
------------------------------
* **The MPC.** The barrier problem of :mod:`mpcrl_lite.mpc.formulation` (eq. 9, tau fixed): on
  the mpcrl side its barrier ``- tau sum log(-h)`` is written into the objective (csnlp
  ``Mpc``, multiple shooting) and the rows of ``h`` are also given to IPOPT as simple bounds
  (on ``b, s, sigma`` and on one nonnegative variable per general row, tied to it by an
  equality), which IPOPT solves with its own barrier driven to
  ``mu_target = 0``: its solution is the barrier problem's, and the solution's ``f`` is the
  barrier value that :class:`mpcrl_lite.mpc.value.MPCValue` uses. The action is the net power
  ``u = b - s`` (an Mpc action with ``u = b - s`` as a constraint), so that mpcrl's Q, which
  fixes the first action, is our ``b_0 - s_0 = a``.
* **theta.** What :class:`mpcrl_lite.learning.qlearning.QLearningUpdater` learns without tying
  (``tie_agents=False``): every part per battery except the constants, and the level of Q as
  one ``T3`` shared by the batteries (a scalar parameter on the mpcrl side); ``phi3`` fixed.
  No bounds (the projection is off on our side).
* **Data.** Transitions ``(s, a, L, s+)`` of the true system
  (:func:`mpcrl_lite.system.battery.step`) at random states and interior actions, under flat
  prices (mpcrl evaluates Q(s, a) and V(s+) of a transition with the same parameters, so the
  price window must not change between them); every transition bootstraps (mpcrl's
  off-policy rollouts do).
* **Update.** mpcrl: ``NewtonMethod(lr)`` with ``hessian_type`` 'approx' or 'full',
  ``update_strategy`` and ``experience`` the transitions of one update; ours:
  :func:`~mpcrl_lite.learning.qlearning.td_gradient` on :class:`~mpcrl_lite.mpc.value.MPCValue`'s
  Q and V and :class:`~mpcrl_lite.learning.qlearning.QLearningUpdater` (``newton_step = lr``).

Run ``python benchmarks/bench_mpcrl_q.py [--transitions 12] [--hessian approx] [--check]
[--n 3] [--horizon 12]``; prints one JSON line (the relative differences of the two updates).

``--hessian full`` on the paper's size (n = 3, N = 12) exhausts the memory on mpcrl's side:
its agent inverts the KKT matrix symbolically (``casadi.solve(Ky, Kp)``, over 17 GB before
``std::bad_alloc`` on a 24 GB machine), so the full Hessian is compared on a smaller MPC of the
same formulation: ``--hessian full --n 2 --horizon 4 --transitions 4``.

The Gauss-Newton matrix of ``S`` transitions has rank at most ``S``, below the ``8 n + 1``
learned parameters for the defaults, so it is singular to rounding (condition 1e23-1e28).
With 12 transitions both sides factorise it only after the first shift (``t = 1e-3``) and agree;
with 24 our Cholesky factorisation happened to succeed at ``t = 0`` (``checks`` in the output),
and the step along the null direction, decided by rounding, differed by 300 times its size:
such a step is not a comparison, hence the default 12. There the TD Hessian
is indefinite (shifted by ``t I`` before the Newton step on both sides) and the two sides
grow ``t`` differently (mpcrl by 1.05 a try, mpcrl_lite doubling), so the comparison gives our
side mpcrl's schedule; it also checks the second derivative of Q against central differences
of its gradient (``checks`` in the JSON line).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

__all__ = ["build_agent", "main", "our_updates", "transitions"]

PRICE_BUY, PRICE_SELL = 60.0, 35.0  # NOK/MWh, flat over the horizon


def transitions(system, count: int, seed: int = 0):
    """``count`` transitions ``(soc, a, L, soc_next)`` of the true system, flat prices."""
    from mpcrl_lite.system.battery import sample_noise, step

    rng = np.random.default_rng(seed)
    n = system.n
    soc = rng.uniform(0.15, 0.85, (count, n))
    a = rng.uniform(-0.45, 0.45, (count, n)) * min(system.U_bar, system.P_bar / n)
    noise = sample_noise(rng, (count, n), system)
    res = step(soc, a, noise, np.full(count, PRICE_BUY), np.full(count, PRICE_SELL), system)
    return soc, a, np.asarray(res.stage_cost), res.soc_next


def build_agent(system, mpc_config, theta0, hessian: str, lr: float, batch: int):
    """mpcrl's ``LstdQLearningAgent`` on the barrier MPC (see the module docstring)."""
    import casadi as cs
    from csnlp import Nlp
    from csnlp.wrappers import Mpc
    from mpcrl import LearnableParameter, LearnableParametersDict, LstdQLearningAgent
    from mpcrl.optim import NewtonMethod

    n, N, tau = system.n, system.N, mpc_config.tau
    nlp = Nlp[cs.SX](sym_type="SX", name="battery_q")
    mpc = Mpc(nlp, prediction_horizon=N, shooting="multi")
    soc, _ = mpc.state("soc", n)
    u, _ = mpc.action("u", n)
    b, _, _ = mpc.variable("b", (n, N), lb=0.0, ub=system.U_bar)
    s, _, _ = mpc.variable("s", (n, N), lb=0.0, ub=system.U_bar)
    shi, _, _ = mpc.variable("sigma_hi", (n, N), lb=0.0)
    slo, _, _ = mpc.variable("sigma_lo", (n, N), lb=0.0)
    parts = ("alpha", "delta", "b", "s", "phi1", "phi2", "T1", "T2")
    th = {name: mpc.parameter(f"theta_{name}", (n, 1)) for name in parts}
    th["phi3"] = mpc.parameter("theta_phi3", (n, 1))
    t3 = mpc.parameter("theta_T3", (1, 1))
    rep = lambda v: cs.repmat(v, 1, N)
    mpc.constraint("net", u, "==", b - s)
    mpc.constraint("dynamics", soc[:, 1:], "==",
                   soc[:, :-1] + rep(th["alpha"]) * (b - s) + rep(th["delta"]))
    # the general rows of h as nonnegative variables tied to them by equalities, so that every
    # logarithm below has a simple bound that IPOPT keeps strictly positive
    slack = {}
    for name, shape in (("grid_b", (1, N)), ("grid_s", (1, N)), ("soc_hi", (n, N)),
                        ("soc_lo", (n, N))):
        slack[name], _, _ = mpc.variable(f"room_{name}", shape, lb=0.0)
    mpc.constraint("grid_b", slack["grid_b"], "==", system.P_bar - cs.sum1(b))
    mpc.constraint("grid_s", slack["grid_s"], "==", system.P_bar - cs.sum1(s))
    mpc.constraint("soc_hi", slack["soc_hi"], "==", system.soc_high + shi - soc[:, 1:])
    mpc.constraint("soc_lo", slack["soc_lo"], "==", soc[:, 1:] + slo - system.soc_low)

    def phi(x):
        return cs.sum1(th["phi1"] * x**2 + th["phi2"] * x + th["phi3"])

    gamma = system.gamma
    (w_hi, w_lo), (wf_hi, wf_lo) = system.omega, system.omega_f
    soc0 = mpc.parameters["soc_0"]  # the measured state (csnlp's initial-state parameter)
    cost = phi(soc[:, 0]) + cs.sum1(w_hi * cs.fmax(soc0 - system.soc_high, 0)
                                    + w_lo * cs.fmax(system.soc_low - soc0, 0))
    for j in range(N):
        cost += gamma**j * cs.sum1((PRICE_BUY + th["b"]) * b[:, j]
                                   - (PRICE_SELL + th["s"]) * s[:, j])
        if j + 1 < N:
            cost += gamma ** (j + 1) * (phi(soc[:, j + 1]) + w_hi * cs.sum1(shi[:, j])
                                        + w_lo * cs.sum1(slo[:, j]))
    last = soc[:, N]
    cost += cs.sum1(th["T1"] * last**2 + th["T2"] * last) + n * t3
    cost += wf_hi * cs.sum1(shi[:, N - 1]) + wf_lo * cs.sum1(slo[:, N - 1])
    # the barrier of every row of h (the formulation's order does not matter for a sum)
    rooms = [b, system.U_bar - b, s, system.U_bar - s, shi, slo, *slack.values()]
    barrier = sum(cs.sum1(cs.sum2(cs.log(r))) for r in rooms)
    mpc.minimize(cost - tau * barrier)
    mpc.init_solver({"print_time": False, "ipopt": {
        "tol": 1e-12, "acceptable_tol": 1e-11, "mu_target": 0.0, "bound_relax_factor": 0.0,
        "nlp_scaling_method": "none", "print_level": 0, "sb": "yes", "max_iter": 3000}},
        "ipopt")
    values = {name: getattr(theta0, name) for name in parts}
    learnable = LearnableParametersDict(
        [LearnableParameter(f"theta_{name}", n, values[name]) for name in parts]
        + [LearnableParameter("theta_T3", 1, float(np.mean(theta0.T3)))])
    class RecordingAgent(LstdQLearningAgent):
        """Keeps theta after every update."""

        thetas: list | None = None

        def on_update(self) -> None:
            if self.thetas is not None:
                self.thetas.append(dict(self.learnable_parameters.value_as_dict))
            super().on_update()

    return RecordingAgent(
        mpc=mpc, update_strategy=batch, discount_factor=gamma,
        optimizer=NewtonMethod(learning_rate=lr), learnable_parameters=learnable,
        fixed_parameters={"theta_phi3": theta0.phi3}, experience=batch,
        hessian_type=hessian, record_td_errors=True,
    ), parts


def our_updates(system, mpc_config, theta0, data, hessian: str, lr: float, batch: int,
                checks: list | None = None):
    """The same updates with mpcrl_lite: thetas after each batch of transitions."""
    from mpcrl_lite.config import LearningConfig
    from mpcrl_lite.learning.qlearning import QLearningUpdater, td_gradient
    from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
    from mpcrl_lite.mpc.formulation import MPC
    from mpcrl_lite.mpc.value import MPCValue

    mpc = MPC(system)
    solver, value = IpoptSolver(mpc, mpc_config), MPCValue(mpc, mpc_config)
    updater = QLearningUpdater(LearningConfig(learner="q", hessian=hessian, newton_step=lr,
                                              tie_agents=False, keep_well_posed=False), system)
    soc, a, cost, soc_next = data
    buy, sell = np.full((batch, mpc.N), PRICE_BUY), np.full((batch, mpc.N), PRICE_SELL)
    theta, out = theta0, []
    for k in range(0, len(cost), batch):
        rows = slice(k, k + batch)
        q = value.action_value(soc[rows], buy, sell, theta, a[rows], hessian=hessian == "full")
        v = value.state_value(solver.solve_batch(soc_next[rows], buy, sell, theta))
        assert q.ok.all() and v.ok.all(), (q.reason, v.reason)
        delta = cost[rows] + system.gamma * v.value - q.value
        g, H = td_gradient(delta, q.grad, q.hess, hessian)
        if checks is not None and hessian == "full":
            # the same direction with the Hessian of Q from central differences of its
            # gradient (an independent check of the KKT-based second derivative)
            d2q = fd_hessian(value, soc[rows], buy, sell, theta, a[rows])
            _, H_fd = td_gradient(delta, q.grad, d2q, hessian)
            d_ours, shift = updater.direction(g, H)
            d_fd, shift_fd = updater.direction(g, H_fd)
            checks.append({"d2Q_rel_diff_fd": float(np.abs(q.hess - d2q).max()
                                                    / np.abs(d2q).max()),
                           "direction_rel_diff_fd": float(np.abs(d_ours - d_fd).max()
                                                          / np.abs(d_fd).max()),
                           "shift": float(shift), "shift_fd": float(shift_fd)})
        theta = updater.step(theta, g, H)
        if checks is not None:
            checks.append({"newton_shift": updater.last_info.get("newton_shift"),
                           "cond": float(np.linalg.cond(updater._basis.T @ H @ updater._basis))})
        out.append(theta)
    return out


def fd_hessian(value, soc, buy, sell, theta, a, eps: float = 1e-5) -> np.ndarray:
    """(S, n_theta, n_theta): central differences of the theta gradient of Q(s, a)."""
    from mpcrl_lite.theta import Theta

    x0 = theta.to_vector()
    cols = []
    for i in range(x0.size):
        grads = []
        for sign in (1.0, -1.0):
            x = x0.copy()
            x[i] += sign * eps
            q = value.action_value(soc, buy, sell, Theta.from_vector(x, theta.n), a)
            assert q.ok.all(), q.reason
            grads.append(q.grad)
        cols.append((grads[0] - grads[1]) / (2 * eps))
    H = np.stack(cols, axis=2)
    return 0.5 * (H + np.swapaxes(H, 1, 2))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transitions", type=int, default=12,
                        help="per update (default 12; see the module docstring on 24)")
    parser.add_argument("--updates", type=int, default=2)
    parser.add_argument("--hessian", choices=("approx", "full"), default="approx")
    parser.add_argument("--lr", type=float, default=0.3)
    parser.add_argument("--check", action="store_true", help="exit 1 above 1e-6 relative")
    parser.add_argument("--n", type=int, default=None,
                        help="batteries (default the paper's 3)")
    parser.add_argument("--horizon", type=int, default=None,
                        help="MPC horizon N (default the paper's 12)")
    args = parser.parse_args(argv)
    from mpcrl_lite.config import MPCConfig, SystemConfig
    from mpcrl_lite.theta import Theta

    sizes = {k: v for k, v in (("n", args.n), ("N", args.horizon)) if v is not None}
    system, mpc_config = SystemConfig(**sizes), MPCConfig()
    theta0 = Theta.nominal(system)
    batch = args.transitions
    data = transitions(system, batch * args.updates)
    agent, parts = build_agent(system, mpc_config, theta0, args.hessian, args.lr, batch)
    soc, a, cost, soc_next = data
    agent.thetas = theirs = []
    rollout = [(soc[i], a[i], float(cost[i]), soc_next[i]) for i in range(len(cost))]
    agent.train_offpolicy([rollout])
    checks: list = []
    # a TD Hessian that is not positive definite (the full one far from a fit, or the
    # Gauss-Newton one of fewer transitions than parameters) is shifted by t I on both sides
    # until its Cholesky factorisation succeeds; mpcrl grows t by 1.05 a try, mpcrl_lite
    # doubles it: the same schedule on both sides, so that the same matrix is solved
    import functools

    from mpcrl_lite.learning import qlearning

    qlearning.regularised_solve = functools.partial(
        qlearning.regularised_solve, growth=1.05, max_tries=5000)
    ours = our_updates(system, mpc_config, theta0, data, args.hessian, args.lr, batch, checks)
    result = {"hessian": args.hessian, "transitions": batch, "n": system.n, "N": system.N,
              "updates": []}
    worst = 0.0
    for k, (mine, p) in enumerate(zip(ours, theirs, strict=False)):
        ref = np.concatenate([np.ravel(p[f"theta_{name}"]) for name in parts]
                             + [np.ravel(p["theta_T3"])])
        got = np.concatenate([getattr(mine, name) for name in parts] + [mine.T3[:1]])
        start = np.concatenate([getattr(theta0, name) for name in parts] + [theta0.T3[:1]])
        rel = float(np.abs((got - start) - (ref - start)).max()
                    / np.abs(ref - start).max())
        worst = max(worst, rel)
        result["updates"].append({"update": k + 1, "step_rel_diff": rel,
                                  "step_norm": float(np.linalg.norm(ref - start))})
    result["updates_compared"] = len(result["updates"])
    if checks:
        result["checks"] = checks
    print(json.dumps(result))
    if args.check and (worst > 1e-6 or len(result["updates"]) < args.updates):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
