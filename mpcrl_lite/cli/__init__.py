"""The command line, ``python -m mpcrl_lite COMMAND ...`` (:mod:`~mpcrl_lite.cli.main`), the
checks it makes before any work (:mod:`~mpcrl_lite.cli.inputs`) and the kernel warm-up
``python -m mpcrl_lite.cli.warm``. The top layer: may import everything below it.
"""
