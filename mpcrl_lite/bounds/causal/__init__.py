"""The best causal policy: it knows the prices, not the future noise.

- :mod:`~mpcrl_lite.bounds.causal.dp`: the stochastic dynamic program over the day;
- :mod:`~mpcrl_lite.bounds.causal.grid`: its discretised battery model and noise expectations;
- :mod:`~mpcrl_lite.bounds.causal.kernels`: its compiled inner loops;
- :mod:`~mpcrl_lite.bounds.causal.mixed`: its grids and Bellman step for batteries that differ;
- :mod:`~mpcrl_lite.bounds.causal.dual`: a Lagrangian lower bound for any number of batteries;
- :mod:`~mpcrl_lite.bounds.causal.table`: stored values of J* with their provenance.

May import: :mod:`mpcrl_lite.system` and below.
"""
