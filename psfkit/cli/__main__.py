"""``python -m psfkit.cli`` (the ``psfkit`` command without an installed entry point)."""

import sys

from psfkit.cli import main

sys.exit(main())
