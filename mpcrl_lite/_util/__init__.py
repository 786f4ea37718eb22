"""Plain helpers below everything else: no model, no MPC, no learning.

- :mod:`~mpcrl_lite._util.jit`: the one numba set-up (cache location and fallback, the
  one-line notice when a kernel compiles) that every compiled kernel uses;
- :mod:`~mpcrl_lite._util.lazy`: modules imported on first use (pandas);
- :mod:`~mpcrl_lite._util.threads`: blocks of independent problems spread over threads, for
  the compiled kernels that release the GIL;
- :mod:`~mpcrl_lite._util.jsonio`: strict JSON from results that hold numpy values, written
  atomically;
- :mod:`~mpcrl_lite._util.stats`: means with Student-t confidence intervals;
- :mod:`~mpcrl_lite._util.validate`: the validators every configuration and command uses;
- :mod:`~mpcrl_lite._util.resources`: where the shipped data and notebooks are;
- :mod:`~mpcrl_lite._util.references`: the cited works and the paper's numbered equations.

May import: nothing of the package.
"""
