"""Every default of the trackers in one place: :class:`TrackerConfig`.

STC, EAKF and EAKF-STC take their constructor defaults from here; ``TrackerConfig.from_dict``
loads a mapping (e.g. a section of a YAML file under ``configs/``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from torchseam.core.config import from_dict

MATLAB_EPS = 2.220446049250313e-16  # eps of the reference implementation's division

PairOrFloat = float | tuple[float, float]


@dataclass
class TrackerConfig:
    """Every default of EAKF-STC in one place (units: px, s, frames).

    Load from a mapping with :meth:`from_dict` (unknown keys and wrong types raise, lists become
    tuples); :meth:`to_dict` gives a plain dict back.
    """

    # --- STC (METHOD.md section 2)
    window: tuple[int, int] = (64, 64)       # context window, twice the target
    target: tuple[int, int] = (32, 32)       # target box around the stripe corner
    alpha: float = 2.25                      # eq. 1 (paper)
    beta: float = 1.0                        # eq. 1 (paper)
    rho: float = 0.075                       # eq. 9 (paper)
    sigma: float | None = None               # eq. 5; None: mean target side
    eps: float = MATLAB_EPS                  # eq. 8 division
    reg: float = 0.0                         # eq. 8 regularised (Wiener): > 0 divides by
                                             # |FFT(prior)|^2 + reg * mean |FFT(prior)|^2
    anchor: float = 0.0                      # weight of the start model in detection (eq. 10)
    anchor_frames: int = 5                   # frames (arc off) averaged into the start model
    scale_update: bool = False               # reference scale update (lambda 0.25, 5 frames)
    scale_lambda: float = 0.25
    scale_frames: int = 5
    peak: str = "subpixel"                   # "subpixel" | "soft" | "argmax"
    temperature: float = 0.05                # soft-argmax temperature
    crop: str = "nearest"                    # "nearest" | "bilinear"
    exclude: int = 5                         # peak area left out of the sidelobe
    # --- EAKF (METHOD.md section 3); q in px^2/s^4, r in px^2
    frame_rate: float = 25.0
    lam: PairOrFloat = 0.3                   # colour of the acceleration (eq. 16)
    a: PairOrFloat = 0.2                     # colour of the position noise (eq. 17)
    b: PairOrFloat = 0.0                     # colour of the displacement noise (eq. 17)
    q: PairOrFloat = 3.0e4                   # ~0.28 px/frame^2 white acceleration at 25 Hz
    r_pos: float = 0.25                      # STC position noise (0.5 px std)
    r_disp: float = 2.0                      # displacement noise: z(k) - z(k-1) of STC
    p0: tuple[float, float, float, float] = (1.0, 2500.0, 1.0, 3.0e4)  # pos, vel, prev, acc
    # --- drift guard (METHOD.md section 4)
    psr0: float = 6.0                        # PSR at which the sharpness test gives 0.5
    psr_slope: float = 4.0                   # per unit of log PSR
    second0: float = 0.75                    # second-peak ratio at which that test gives 0.5
    second_slope: float = 15.0
    gate: float = 4.0                        # Mahalanobis gate (sigmas)
    gate_slope: float = 2.0                  # per sigma
    spread0: float = 1.0                     # gate size (px) with no penalty ...
    spread_slope: float = 2.0                # ... and the penalty's log slope (PDA: 2)
    r_scale_max: float = 1.0e3               # R inflation of a fully distrusted measurement
    r_trust: float = 0.65                    # log R scale = log r_scale_max * ...
    r_slope: float = 8.0                    # ... sigmoid(r_slope (r_trust - trust))
    learn_trust: float = 0.75                # rho scale = sigmoid(learn_slope (trust - this))
    learn_slope: float = 20.0
    # --- status
    max_coast: int = 15                      # coasting frames before LOST
    lost_std: float = 10.0                   # position std (px) beyond which LOST
    learnable: bool = True
    timing_window: int = 100_000             # step timings kept

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None = None, **overrides: Any
                  ) -> TrackerConfig:
        """Build from a mapping (plus keyword overrides), read by core's config reader: lists
        become tuples, an unknown field or a value of the wrong type raises
        :class:`~torchseam.core.config.ConfigError` naming it (the trackers check the ranges).

        Example:
            >>> TrackerConfig.from_dict({"rho": 0.05, "window": [48, 48]}).window
            (48, 48)
        """
        return from_dict(cls, {**(data or {}), **overrides}, "tracker config")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
