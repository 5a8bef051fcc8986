"""``python -m ekdun.cli`` (used with ``torchrun -m ekdun.cli train ...``)."""

import sys

from ekdun.cli import main

sys.exit(main())
