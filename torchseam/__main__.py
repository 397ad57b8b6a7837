"""``python -m torchseam``: the ``torchseam`` command."""

from torchseam.cli import run_command

if __name__ == "__main__":
    run_command()
