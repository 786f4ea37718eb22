"""One MPC and one learner per battery, the shared grid limit coordinated by prices.

- :mod:`~mpcrl_lite.decentralized.local_qp`: the local MPCs' barrier problems;
- :mod:`~mpcrl_lite.decentralized.coordination` (compiled in
  :mod:`~mpcrl_lite.decentralized.coordination_kernel`): the grid prices found by a
  decomposed Newton method;
- :mod:`~mpcrl_lite.decentralized.learner`: the decentralized learning experiment.

May import: :mod:`mpcrl_lite.learning` and below.
"""
