"""The ``torchseam`` command line.

Each stage of the data flow registers its own sub-commands from a ``cli.py`` module of its own
(``register(subparsers)``), so this file only lists them: :data:`COMMANDS` gives each command's
name, module and one-line help, so ``torchseam --help`` (and ``--version``) imports no stage; a
stage module is imported only when its command runs (or shows its own ``--help``).
``tests/test_package.py`` checks the table against what the modules register.

Every bad input ends the same way: one line on stderr naming the file, field, frame or option
(``torchseam COMMAND: error: ...``), nothing on stdout, exit code 2. The argument types below
(:func:`seed_arg`, :func:`out_dir_arg`, :func:`model_arg`, :func:`segments_arg`, defined in
:mod:`torchseam.core.cliargs` and re-exported here) let the sub-commands refuse bad options
before any work starts.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, NoReturn

from torchseam import CONFIGS_ENV, MODELS_ENV, config_dir, model_dir
from torchseam.core.cliargs import (
    MAX_SEED,
    SEGMENT_LETTERS,
    OneLineParser,
    config_dir_arg,
    model_arg,
    out_dir_arg,
    out_file_arg,
    seed_arg,
    segments_arg,
    threads_arg,
)
from torchseam.core.errors import TorchseamError

#: the argument types live in :mod:`torchseam.core.cliargs` (stage modules import them from
#: there); re-exported here for callers of the command line's module
__all__ = ["COMMANDS", "COMMAND_MODULES", "MAX_SEED", "SEGMENT_LETTERS", "OneLineParser",
           "build_parser", "config_dir_arg", "main", "model_arg", "out_dir_arg", "out_file_arg",
           "seed_arg", "segments_arg", "threads_arg", "use_config_dir", "run_command"]

#: Every sub-command: name, the stage module whose ``register(subparsers)`` adds it, and its
#: one-line help (the same text the module gives ``add_parser``), in the order ``--help`` lists
#: them. A module adding several commands lists them next to each other.
COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("simulate", "torchseam.sim.cli",
     "render a simulated laser-sensor sequence with ground truth"),
    ("detect", "torchseam.vision.cli",
     "find the weld feature point in frames (TIPM, clean frames)"),
    ("track", "torchseam.track.cli", "track the feature point through a folder of frames"),
    ("eval", "torchseam.track.cli", "track a labelled folder and print the error table"),
    ("train", "torchseam.fit.cli", "fit the EAKF-STC parameters on labelled sequences"),
    ("train-live", "torchseam.fit.anchored_cli",
     "fit the live tracker (EAKF-STC and the fusion) end to end on full sequences"),
    ("calibrate", "torchseam.live.calibrate_cli",
     "calibrate camera, laser plane, hand-eye or TCP from a folder"),
    ("ring", "torchseam.live.ring_cli",
     "locate and plan the whole ring in open loop; error table and plots"),
    ("plan", "torchseam.plan.cli",  # placement, segments, torch angles; pre-flight gate check
     "plan a part's weld and check every pose with the reachability gate"),
    ("robot", "torchseam.robot.cli",  # fk | ik | check | sim-controller
     "IRB 1410 kinematics, reachability checks and the EGM link"),
    ("demo", "torchseam.live.cli",
     "weld a simulated part (default the T joint) in closed loop and write a report"),
    ("replay", "torchseam.live.cli",
     "feed recorded frames (folder, video or camera) through the live loop, open loop"),
    ("weld", "torchseam.live.cell_cli",
     "weld a cell: camera frames and the controller's EGM in, poses and the arc out"),
    ("virtual-cell", "torchseam.live.cell_cli",
     "a simulated IRC5 and laser camera in their own processes"),
    ("console", "torchseam.console.cli",
     "operator console: a local web page to run and watch the weld"),
    ("config", "torchseam.config_show",
     "show every setting's effective value and where it came from"),
)
#: Stage modules that add sub-commands, in the order ``--help`` lists them.
COMMAND_MODULES = tuple(dict.fromkeys(module for _, module, _ in COMMANDS))

# --------------------------------------------------------------------------- the command

class _VersionAction(argparse.Action):
    """``--version``: the installed package's version (its metadata, read only when asked)."""

    def __init__(self, option_strings: list[str], dest: str, **kw: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kw)

    def __call__(self, parser: argparse.ArgumentParser, *_: Any) -> NoReturn:
        import torchseam

        print(f"{parser.prog} {torchseam.__version__}")
        parser.exit(0)


def build_parser(commands: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The ``torchseam`` parser. ``commands``: the sub-commands whose stage modules are imported
    to give them their options (None: all); the others are listed from :data:`COMMANDS` alone
    (their name and help: enough for ``torchseam --help`` and to pick the command)."""
    wanted = {name for name, _, _ in COMMANDS} if commands is None else set(commands)
    modules = {module for name, module, _ in COMMANDS if name in wanted}
    parser = OneLineParser(
        prog="torchseam",
        description="Laser-vision seam tracking of pipe-to-pipe welds (EAKF-STC) in torch.",
        epilog=f"configs: {config_dir()}\nmodels:  {model_dir()}\n\n"
               "Your own configs: copy the configs folder, edit the copy and run\n"
               f"  torchseam --config-dir COPY COMMAND ...   (or set {CONFIGS_ENV}=COPY);\n"
               f"your own fitted model: --model FILE, or {MODELS_ENV}=DIR.\n"
               "A command's options: torchseam COMMAND --help",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action=_VersionAction,
                        help="print the installed version and exit")
    parser.add_argument("--config-dir", type=config_dir_arg, metavar="DIR",
                        help="read every config from DIR instead of the shipped configs (a "
                             f"full copy of them, edited; default ${CONFIGS_ENV}, else the "
                             "shipped ones, listed below)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=OneLineParser)
    registered: set[str] = set()
    for name, module, text in COMMANDS:
        if module not in modules:
            sub.add_parser(name, help=text, add_help=False)  # its options are not read here
        elif module not in registered:
            registered.add(module)
            importlib.import_module(module).register(sub)
    return parser


@contextlib.contextmanager
def use_config_dir(path: Path | None) -> Iterator[None]:
    """Read the configs from ``path`` while the block runs (None: leave them as they are):
    ``$TORCHSEAM_CONFIGS`` is set for the block, and every loader locates its file when it
    reads it (:func:`torchseam.core.config.config_path`); no module attribute is touched."""
    if path is None:
        yield
        return
    old_env = os.environ.get(CONFIGS_ENV)
    os.environ[CONFIGS_ENV] = str(path)
    try:
        yield
    finally:
        if old_env is None:
            os.environ.pop(CONFIGS_ENV, None)
        else:
            os.environ[CONFIGS_ENV] = old_env


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, run the command's ``func(args)``, turn known errors into messages:
    a :class:`TorchseamError` (a config's ``ConfigError`` included) or a file the system
    refused (:class:`OSError` naming it) is one line on stderr and exit code 2.

    Parses twice: first with the table alone (``--help``, ``--version``, ``--config-dir`` and
    which command; no stage imported), then, with the config folder in place, with the chosen
    command's module imported for its options."""
    argv = list(sys.argv[1:] if argv is None else argv)
    first, _ = build_parser(commands=()).parse_known_args(argv)
    with use_config_dir(first.config_dir):
        args = build_parser(commands=(first.command,)).parse_args(argv)
        return _run(args)


def _run(args: argparse.Namespace) -> int:
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
        # a second Ctrl-C (a terminal's, or one a wrapper such as `timeout` passes on) while
        # this is said would be a traceback: ignored while the line is written
        main_thread = threading.current_thread() is threading.main_thread()
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN) if main_thread else None
        try:
            print(f"torchseam {args.command}: interrupted", file=sys.stderr)
        finally:
            if main_thread:
                signal.signal(signal.SIGINT, handler)
        return 130
    return int(rc or 0)


def run_command() -> NoReturn:
    """The ``torchseam`` program (the console script and ``python -m torchseam``): :func:`main`,
    then exit with its code. Once a command was interrupted the process only ends, so further
    Ctrl-Cs are ignored (one arriving while the interpreter shuts down is a traceback)."""
    rc = main()
    if rc == 130 and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(rc)


if __name__ == "__main__":
    run_command()
