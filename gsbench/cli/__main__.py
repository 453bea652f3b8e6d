"""``python -m gsbench.cli``: the same as the ``gsbench`` console script."""

import sys

from gsbench.cli import main

sys.exit(main())
