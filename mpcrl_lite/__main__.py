"""``python -m mpcrl_lite``: see :mod:`mpcrl_lite.cli`."""

import sys

from .cli import main

sys.exit(main())
