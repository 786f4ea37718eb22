"""Parameter sweeps: a grid of learning runs, serially or on Dask, into one tidy table.

- :mod:`~mpcrl_lite.studies.sweep.api`: :func:`~mpcrl_lite.studies.sweep.api.run_sweep`;
- :mod:`~mpcrl_lite.studies.sweep.grid`: read and validate a grid, build every run;
- :mod:`~mpcrl_lite.studies.sweep.run`: grid points as executed on a worker;
- :mod:`~mpcrl_lite.studies.sweep.schedule`: where the runs execute;
- :mod:`~mpcrl_lite.studies.sweep.store`: the output directory;
- :mod:`~mpcrl_lite.studies.sweep.table`: the results table.
"""
