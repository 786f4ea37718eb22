"""The one closed loop: a policy acting on the true system, and the one record of it.

- :mod:`~mpcrl_lite.sim.closed_loop`: :func:`~mpcrl_lite.sim.closed_loop.simulate` (with
  hooks), the MPC-as-policy adapter, :func:`~mpcrl_lite.sim.closed_loop.run_month`,
  :func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc`;
- :mod:`~mpcrl_lite.sim.compiled_month` (the template :mod:`~mpcrl_lite.sim.month_kernel`): the
  same loop for a month of the compiled MPC in one compiled call, the record bit for bit,
  where it covers the month (``run_month`` and ``evaluate_mpc`` choose it);
- :mod:`~mpcrl_lite.sim.candidates`: many thetas x days x noise draws in one closed loop
  (:func:`~mpcrl_lite.sim.candidates.evaluate_candidates`, common random numbers);
- :mod:`~mpcrl_lite.sim.record`: every array of a simulated period;
- :mod:`~mpcrl_lite.sim.exploration` (compiled in
  :mod:`~mpcrl_lite.sim.exploration_kernel`): what a learner commands around the policy.

May import: :mod:`mpcrl_lite.mpc` and below.
"""
