"""``python -m tests.reference``: runs :mod:`reference.cli` under the package's one import name.

The package is imported as ``reference`` (``tests/`` on ``sys.path``, as pytest does) so that
numba's on-disk cache always refers to the same module names.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reference.cli import main  # noqa: E402

raise SystemExit(main())
