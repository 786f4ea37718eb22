"""``python -m mpcrl_lite``: see :mod:`mpcrl_lite.cli.main`."""

import sys

from .cli.main import end_process, main

# a command that returns ends the process at once (end_process: its threads and exit handlers
# first); an error that escapes main ends it the usual way, with its traceback
sys.exit(end_process(main()))
