"""``python -m mpcrl_lite``: see :mod:`mpcrl_lite.cli.main`."""

import sys

from .cli.main import main

sys.exit(main())
