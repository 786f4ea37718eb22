"""The paper's MPC (eq. 9) as a policy: one formulation, its solutions, its sensitivity.

- :mod:`~mpcrl_lite.mpc.formulation`: the MPC written once in CasADi, its QP data and the
  barrier KKT conditions;
- :mod:`~mpcrl_lite.mpc.solution`: what every back-end returns, and the base they share;
- :mod:`~mpcrl_lite.mpc.sensitivity`: the policy sensitivity d pi / d theta (eq. 20);
- :mod:`~mpcrl_lite.mpc.backends`: the solvers (IPOPT reference, numpy batch, compiled
  kernel) and :func:`~mpcrl_lite.mpc.backends.registry.make_solver`.

May import: :mod:`mpcrl_lite.system` and below.
"""
