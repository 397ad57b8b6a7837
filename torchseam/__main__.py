"""``python -m torchseam``: the ``torchseam`` command."""

import sys

from torchseam.cli import main

if __name__ == "__main__":
    sys.exit(main())
