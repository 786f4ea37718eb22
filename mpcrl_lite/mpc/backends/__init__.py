"""The MPC's solver back-ends; each returns the types of :mod:`mpcrl_lite.mpc.solution`.

- :mod:`~mpcrl_lite.mpc.backends.ipopt`: IPOPT through CasADi, the reference;
- :mod:`~mpcrl_lite.mpc.backends.batch` (with :mod:`~mpcrl_lite.mpc.backends.batch_kkt`,
  :mod:`~mpcrl_lite.mpc.backends.batch_adjoint`, :mod:`~mpcrl_lite.mpc.backends.batch_linalg`):
  a numpy interior point over all days at once;
- :mod:`~mpcrl_lite.mpc.backends.kernel` (with its compiled
  :mod:`~mpcrl_lite.mpc.backends.kernel_core`): the same iteration compiled with numba;
- :mod:`~mpcrl_lite.mpc.backends.registry`: the back-ends by name and
  :func:`~mpcrl_lite.mpc.backends.registry.make_solver`.

Back-ends never import each other; only the registry imports them all.
May import: the rest of :mod:`mpcrl_lite.mpc` and below.
"""
