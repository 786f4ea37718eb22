"""One module per command of ``python -m mpcrl_lite``: each has ``NAME``, ``HELP``,
``add_parser(sub)`` (its options) and ``run(args)`` (the work; returns the exit status).
:data:`COMMANDS` lists them in the order ``--help`` shows.
"""

from . import baselines, evaluate, learn, report, simulate, study, sweep, tune

#: The command modules, in the order of ``--help``.
COMMANDS = (simulate, learn, report, baselines, evaluate, sweep, study, tune)
