"""What a learned policy is measured against: baselines and the best causal policy.

- :mod:`~mpcrl_lite.bounds.scenario`: the common draws every policy is judged on;
- :mod:`~mpcrl_lite.bounds.rule`: the price rule;
- :mod:`~mpcrl_lite.bounds.clairvoyant`: the clairvoyant lower bound (it knows the noise);
- :mod:`~mpcrl_lite.bounds.baselines`: the nominal MPC, the price rule, a learned theta, the
  clairvoyant bound and J* side by side (and the ``baselines`` command);
- :mod:`~mpcrl_lite.bounds.causal`: the best causal policy J* (dynamic programming, its
  grid, a Lagrangian lower bound, the stored table).

May import: :mod:`mpcrl_lite.learning` and below.
"""
