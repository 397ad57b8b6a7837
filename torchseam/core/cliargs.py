"""The command line's argument types, shared by every stage's ``cli.py``.

Stage modules take them from here, not from :mod:`torchseam.cli` (the top of the layers: no
stage imports it); :mod:`torchseam.cli` re-exports them. Each type refuses a bad option before
any work starts (``argparse.ArgumentTypeError``: one line, exit code 2 through
:class:`OneLineParser`). Nothing heavy is imported here: ``torchseam --help`` stays fast.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

__all__ = ["MAX_SEED", "SEGMENT_LETTERS", "OneLineParser", "config_dir_arg", "model_arg",
           "out_dir_arg", "out_file_arg", "seed_arg", "segments_arg", "threads_arg"]

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


def number_arg(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
               what: str = "a number") -> Callable[[str], float]:
    """An argument type for a finite number in ``[lo, hi]`` (``lo_open``: above ``lo``), whose
    refusal names ``what`` the option takes: ``number_arg(0, lo_open=True, what="a length in
    mm")``."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected {what}") from None
        ok = math.isfinite(v) and (lo is None or (v > lo if lo_open else v >= lo)) and (
            hi is None or v <= hi)
        if not ok:
            rng = (f"> {lo:g}" if lo_open else f">= {lo:g}") if lo is not None else ""
            rng = f"{lo:g} .. {hi:g}" if lo is not None and hi is not None and not lo_open \
                else (rng + (f" and <= {hi:g}" if hi is not None else "")).strip()
            raise argparse.ArgumentTypeError(f"{text!r}: expected {what}, {rng}")
        return v

    return parse


def threads_arg(text: str) -> int:
    """``--threads``: a whole number >= 1 (torch refuses 0 and below)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text}: use 1 or more threads")
    return n


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
    try:
        out_dir_arg(str(p.parent))
    except argparse.ArgumentTypeError as e:  # name the file asked for, then its folder
        raise argparse.ArgumentTypeError(f"{text}: {e}") from None
    return p


def model_arg(text: str) -> Path:
    """``--model``: an existing tracker model file (its content is checked when loaded)."""
    p = Path(text)
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such model file")
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"{text} is not a file (expected a tracker model, "
                                         "e.g. models/live_tracker.safetensors)")
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


def config_dir_arg(text: str) -> Path:
    """``--config-dir``: an existing folder (made absolute: the command may change folder)."""
    p = Path(text).expanduser()
    if not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such folder" if not p.exists()
                                         else f"{text} is a file, not a folder")
    return p.resolve()
