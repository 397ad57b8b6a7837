"""The ``torchseam`` command line.

Each stage of the data flow registers its own sub-commands from a ``cli.py`` module of its own
(``register(subparsers)``), so this file only lists them.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from torchseam.core.errors import TorchseamError

#: Stage modules that add sub-commands, in the order ``--help`` lists them.
COMMAND_MODULES = (
    "torchseam.sim.cli",       # simulate
    "torchseam.vision.cli",    # detect
    "torchseam.track.cli",     # track, eval
    "torchseam.fit.cli",       # train
    "torchseam.geometry.calib_cli",  # calibrate
    "torchseam.live.ring_cli",  # ring
    "torchseam.robot.cli",     # robot fk | ik | check | sim-controller
    "torchseam.live.cli",      # demo
    "torchseam.console.cli",   # console
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchseam",
        description="Laser-vision seam tracking of pipe-to-pipe welds (EAKF-STC) in torch.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, run the command's ``func(args)``, turn known errors into messages."""
    args = build_parser().parse_args(argv)
    try:
        rc = args.func(args)
    except TorchseamError as e:
        print(f"torchseam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchseam {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
