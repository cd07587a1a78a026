"""``python -m urhead``: the ``urhead`` command line."""

import sys

from urhead.cli import main

sys.exit(main())
