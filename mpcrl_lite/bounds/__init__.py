"""What a learned policy is measured against: baselines and the best causal policy.

- :mod:`~mpcrl_lite.bounds.baselines`: the clairvoyant bound, the nominal MPC, the price rule
  and a learned theta on the same draws;
- :mod:`~mpcrl_lite.bounds.causal`: the best causal policy J* (dynamic programming, its
  grid, a Lagrangian lower bound, the stored table).

May import: :mod:`mpcrl_lite.learning` and below.
"""
