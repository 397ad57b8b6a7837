"""Errors a user can act on. The CLI prints their message, never a traceback."""

from __future__ import annotations


class TorchseamError(Exception):
    """Base of every error that names a user-fixable problem (file, field, frame index)."""


class DatasetError(TorchseamError):
    """A dataset folder, frame or label file is missing or malformed."""


class FrameError(TorchseamError):
    """A frame cannot be used: wrong size, wrong channels, unreadable."""
