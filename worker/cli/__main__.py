"""``python -m worker.cli``: the same as ``osdar-ar``."""

import sys

from worker.cli import main

sys.exit(main())
