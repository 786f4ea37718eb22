"""Many learning runs: multi-seed studies, lockstep runs, sweeps, transfer to new prices.

- :mod:`~mpcrl_lite.studies.study`: one learning run over many seeds, judged against J*;
- :mod:`~mpcrl_lite.studies.lockstep`: K runs stepped together in one process;
- :mod:`~mpcrl_lite.studies.transfer`: a learned theta on prices it never saw;
- :mod:`~mpcrl_lite.studies.sweep`: parameter grids, serially or on Dask.

A sweep may execute a report notebook per run, so this layer sits above
:mod:`mpcrl_lite.publish`. May import: :mod:`mpcrl_lite.publish` and below.
"""
