"""Fit the EAKF-STC tracker's parameters on labelled sequences (see ``torchseam train --help``).

    python train/fit_tracker.py --generate 16 --levels heavy,strike --frames 150
    torchrun --nproc_per_node 2 train/fit_tracker.py --generate 16 --levels heavy,strike
"""

import sys

from torchseam.fit.cli import main

if __name__ == "__main__":
    sys.exit(main())
