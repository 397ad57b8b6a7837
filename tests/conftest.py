"""Shared fixtures: the shipped configs and small simulated batches (made once per session)."""

from __future__ import annotations

import cv2
import pytest
import torch

from torchseam.core.config import load_cell, load_noise, load_part

# Small CPU ops: one thread each is fastest and keeps timings stable on 2-core CI.
torch.set_num_threads(1)
cv2.setNumThreads(1)


@pytest.fixture(scope="session")
def cell():
    return load_cell()


@pytest.fixture(scope="session")
def part():
    return load_part()


@pytest.fixture(scope="session")
def noise():
    return load_noise()


@pytest.fixture(scope="session")
def clean_seq(cell, part, noise):
    """A short clean sequence in memory: list of (frame, truth)."""
    from torchseam.sim.sequence import SequenceSpec, simulate

    return list(simulate(cell, part, noise, SequenceSpec(n_frames=12, level=0.0, seed=3)))


@pytest.fixture(scope="session")
def parts():
    """The shipped settings and parts of the live stack (plan, live, search, egm, the arm,
    TIPM, ECAL): what the command line hands ``run_demo``, ``run_ring`` and ``run_replay``."""
    from torchseam.live.parts import load_live_parts

    return load_live_parts()


@pytest.fixture(scope="session")
def tipm(parts):
    """TIPM with the shipped ``configs/tipm.yaml``."""
    return parts.tipm
