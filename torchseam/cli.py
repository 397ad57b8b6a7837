"""The ``torchseam`` command line.

Each stage of the data flow registers its own sub-commands from a ``cli.py`` module of its own
(``register(subparsers)``), so this file only lists them.

Every bad input ends the same way: one line on stderr naming the file, field, frame or option
(``torchseam COMMAND: error: ...``), nothing on stdout, exit code 2. The argument types below
(:func:`seed_arg`, :func:`out_dir_arg`, :func:`model_arg`, :func:`segments_arg`) let the
sub-commands refuse bad options before any work starts.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path
from typing import NoReturn

from torchseam.core.errors import TorchseamError

#: Stage modules that add sub-commands, in the order ``--help`` lists them.
COMMAND_MODULES = (
    "torchseam.sim.cli",       # simulate
    "torchseam.vision.cli",    # detect
    "torchseam.track.cli",     # track, eval
    "torchseam.fit.cli",       # train
    "torchseam.geometry.calib_cli",  # calibrate
    "torchseam.live.ring_cli",  # ring
    "torchseam.plan.cli",      # plan (placement, segments, torch angles; pre-flight gate check)
    "torchseam.robot.cli",     # robot fk | ik | check | sim-controller
    "torchseam.live.cli",      # demo
    "torchseam.console.cli",   # console
)

#: largest seed the commands take (NumPy, torch and OpenCV all accept it)
MAX_SEED = 2**31 - 1
#: the six weld segments of the ring (``--segments``)
SEGMENT_LETTERS = "abcdef"


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, ``PROG: error: MESSAGE``, exit code 2
    (argparse's own print the usage first; ``--help`` still shows it)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# --------------------------------------------------------------------------- argument types

def seed_arg(text: str) -> int:
    """``--seed``: a whole number 0 .. :data:`MAX_SEED`."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 0 <= seed <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"{text} is out of range: use 0 .. {MAX_SEED}")
    return seed


def out_dir_arg(text: str) -> Path:
    """An output folder: an existing folder, or a path whose nearest existing parent is a
    folder this process may write into (so a run does not fail at its end)."""
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, not a folder")
    anc = p if p.exists() else next((a for a in p.absolute().parents if a.exists()), None)
    if anc is None or not anc.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {anc} is not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: no permission to write into {anc}")
    return p


def out_file_arg(text: str) -> Path:
    """An output file: not a folder, in a folder that exists or can be made and written."""
    p = Path(text)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    out_dir_arg(str(p.parent))
    return p


def model_arg(text: str) -> Path:
    """``--model``: an existing EAKF-STC model file (its content is checked when loaded)."""
    p = Path(text)
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such model file")
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"{text} is not a file (expected an EAKF-STC model, "
                                         "e.g. models/eakf_stc.safetensors)")
    return p


def segments_arg(text: str) -> str:
    """``--segments``: letters of ``abcdef``, each at most once (e.g. ``ace``)."""
    bad = sorted(set(text) - set(SEGMENT_LETTERS))
    if not text or bad:
        what = f"unknown letter {bad[0]!r}" if bad else "no letters"
        raise argparse.ArgumentTypeError(f"{text!r}: {what}; use letters from "
                                         f"{SEGMENT_LETTERS}, e.g. ace")
    twice = sorted({c for c in text if text.count(c) > 1})
    if twice:
        raise argparse.ArgumentTypeError(f"{text!r}: segment {twice[0]!r} is given twice; "
                                         "name each segment once")
    return text


# --------------------------------------------------------------------------- the command

def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="torchseam",
        description="Laser-vision seam tracking of pipe-to-pipe welds (EAKF-STC) in torch.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=OneLineParser)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, run the command's ``func(args)``, turn known errors into messages:
    a :class:`TorchseamError` (a config's ``ConfigError`` included) or a file the system
    refused (:class:`OSError` naming it) is one line on stderr and exit code 2."""
    args = build_parser().parse_args(argv)
    try:
        rc = args.func(args)
    except TorchseamError as e:
        print(f"torchseam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.filename is None:  # not about a file the user named: a real failure
            raise
        print(f"torchseam {args.command}: error: {e.filename}: {e.strerror or e}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchseam {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
