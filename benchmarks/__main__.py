"""``python -m benchmarks``: every benchmark side by side in one run (see :mod:`benchmarks.fit`)."""

import sys

from benchmarks.fit import main

sys.exit(main())
