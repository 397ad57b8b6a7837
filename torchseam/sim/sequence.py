"""Sequences of simulated frames: the sensor rides along the seam at weld speed and frame rate.

The robot follows the *nominal* (design) seam with a small path wobble, while the true part
deviates from the design; so the feature point wanders in the image the way it does in a real
cell. Every frame carries its ground truth (:class:`FrameTruth`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from torchseam.core.config import CellConfig, NoiseConfig, PartConfig
from torchseam.core.transforms import apply, invert, rotation_about
from torchseam.sim.noise import ARC_BGR, SPATTER_BGR, STRIPE_BGR, ArcNoise, NoiseFlags
from torchseam.sim.scene import Scene
from torchseam.sim.sensor import LaserSensor, camera_pose

BACKGROUND_GREY = 6.0       # ambient light behind the band-pass filter
WOBBLE_MM = 0.15            # robot path wobble (std, smooth)
WOBBLE_DEG = 0.15
# (B, G, R) <- (stripe, glare, spatter) grey layers
COLOUR_MIX = np.stack([STRIPE_BGR, ARC_BGR, SPATTER_BGR], axis=1).astype(np.float32)


@dataclass
class FrameTruth:
    """Ground truth of one frame (positions in the robot base frame {B}, mm)."""

    index: int
    t_s: float
    uv: np.ndarray             # (2,) feature pixel
    visible: bool              # the seam point is lit, unoccluded and inside the image
    laser_on: bool
    arc_on: bool               # the welding arc burns (arc noise applies)
    seam_B: np.ndarray         # (3,) true 3D seam point on the stripe
    arm_B: np.ndarray          # (2, 3) points on the branch arm and on the main arm
    arm_uv: np.ndarray         # (2, 2)
    T_B_C: np.ndarray          # (4, 4) camera pose
    T_B_W: np.ndarray          # (4, 4) torch TCP pose
    arc_uv: np.ndarray         # (2,) where the arc (torch tip) projects
    flags: NoiseFlags = field(default_factory=NoiseFlags)


@dataclass
class SequenceSpec:
    """What to simulate. ``start_mm`` is the nominal seam arc length at frame 0 (None: random)."""

    n_frames: int = 300
    level: float = 0.0
    seed: int = 0
    start_mm: float | None = None
    rotation_deg: float = 0.0
    wobble: bool = True
    laser_off: tuple[int, ...] = ()
    arc_on_frame: int | None = None   # first frame with the arc burning (None: noise config)
    t0_s: float = 0.0                 # weld time at frame 0 (the part's thermal drift)


class SensorRenderer:
    """Renders what the sensor sees from any torch pose: the frame and its ground truth.

    The arc-noise state (flicker, bursts, reflections) carries over calls, so successive calls
    form a sequence. :func:`simulate` drives it along the nominal path; the closed-loop demo
    drives it from wherever the simulated robot actually is.

    Args:
        scene: the part (true and nominal) on its positioner.
        level: arc-noise level in [0, 1]; seed: random seed.
    """

    def __init__(self, cell: CellConfig, scene: Scene, noise: NoiseConfig, level: float,
                 seed: int) -> None:
        self.cell, self.scene = cell, scene
        self.rng = np.random.default_rng(seed)
        self.sensor = LaserSensor(cell)
        w, h = cell.camera.width, cell.camera.height
        self.size = (w, h)
        self.arc_noise = ArcNoise(noise, level, (w, h), int(self.rng.integers(2**31)))
        self.clean = ArcNoise(noise, 0.0, (w, h), 0)
        self.sigma_clean = noise.sensor.sigma_clean
        self.background = _background(self.rng, w, h)
        self.read_noise = [self.rng.standard_normal((h + 16, w + 16, 3), dtype=np.float32)
                           for _ in range(4)]
        self._tmp = np.empty((h, w, 3), np.float32)
        self.k = 0

    def render(self, T_B_W: np.ndarray, t_s: float, arc_on: bool = True, laser_on: bool = True,
               phi_hint: float | None = None, force_flash: bool = False
               ) -> tuple[np.ndarray, FrameTruth]:
        """Frame (H, W, 3) uint8 and truth with the torch at ``T_B_W`` at weld time ``t_s``.

        ``phi_hint``: branch angle near the stripe (default: from the torch position).
        ``force_flash``: blind the sensor with an arc flash this frame (fault injection).
        """
        scene, sensor, rng = self.scene, self.sensor, self.rng
        w, h = self.size
        T_B_C = camera_pose(self.cell, T_B_W)
        T_B_T = scene.part_pose(t_s)
        T_T_C = invert(T_B_T) @ T_B_C
        if phi_hint is None:
            p_T = apply(invert(T_B_T), T_B_W[:3, 3])
            phi_hint = float(np.arctan2(p_T[1], p_T[0]))
        view = sensor.view(scene.true_joint, T_T_C, phi_hint)
        # the arc burns at the torch tip
        arc_uv = sensor.project(apply(invert(T_B_C), T_B_W[:3, 3])[None])[0]
        src = self.arc_noise if arc_on else self.clean
        centre = np.array([w / 2.0, h / 2.0])
        layers = src.next(arc_uv, view.seam_uv if np.all(np.isfinite(view.seam_uv)) else centre)
        if force_flash:
            layers.glare += 400.0
            layers.flags.flash = True
        stripe = (sensor.stripe_layer(view, rng, layers.gaps) if laser_on
                  else np.zeros((h, w), np.float32))
        # colour mixing of stripe, arc glare and spatter light in one pass
        img = cv2.transform(cv2.merge([stripe, layers.glare, layers.spatter]), COLOUR_MIX)
        img += self.background
        dy, dx = rng.integers(0, 16, 2)
        sigma = src.sensor_sigma() if arc_on else self.sigma_clean
        # sigma * noise into a reused buffer, then added: the same numbers, no temporaries
        np.multiply(self.read_noise[self.k % 4][dy:dy + h, dx:dx + w], sigma, out=self._tmp)
        img += self._tmp
        frame = np.clip(img, 0, 255, out=img).astype(np.uint8)
        truth = FrameTruth(
            index=self.k, t_s=t_s, uv=view.seam_uv, visible=view.visible and laser_on,
            laser_on=laser_on, arc_on=arc_on, seam_B=apply(T_B_T, view.seam_T),
            arm_B=apply(T_B_T, view.arm_T), arm_uv=view.arm_uv, T_B_C=T_B_C, T_B_W=T_B_W,
            arc_uv=arc_uv, flags=layers.flags)
        self.k += 1
        return frame, truth


def simulate(cell: CellConfig, part: PartConfig, noise: NoiseConfig, spec: SequenceSpec
             ) -> Iterator[tuple[np.ndarray, FrameTruth]]:
    """Yield ``(frame, truth)`` pairs: (H, W, 3) uint8 BGR frames with their ground truth.

    The robot runs the nominal path at weld speed (with a small wobble). The first
    ``noise.clean_lead_frames`` frames (or up to ``spec.arc_on_frame``) are arc-off (clean),
    as before a real weld starts; then the arc noise of ``spec.level`` applies.

    Example:
        >>> from torchseam.core.config import load_cell, load_part, load_noise
        >>> frames = simulate(load_cell(), load_part(), load_noise(), SequenceSpec(n_frames=2))
        >>> img, truth = next(frames)
        >>> img.shape, truth.visible
        ((492, 656, 3), True)
    """
    if spec.n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {spec.n_frames}")
    rng = np.random.default_rng(spec.seed)
    scene = Scene(part, spec.rotation_deg)
    proc = cell.process
    start = rng.uniform(0, scene.seam_length_mm) if spec.start_mm is None else spec.start_mm
    renderer = SensorRenderer(cell, scene, noise, spec.level, int(rng.integers(2**31)))
    wob = np.zeros(6)
    arc_on_frame = noise.clean_lead_frames if spec.arc_on_frame is None else spec.arc_on_frame
    a = 0.97  # wobble correlation per frame
    for k in range(spec.n_frames):
        t = k / proc.frame_rate_hz
        s = start + proc.weld_speed_mm_s * t
        T_B_W = scene.nominal_tcp(np.array([s]))[0]
        if spec.wobble:
            wob = a * wob + np.sqrt(1 - a * a) * rng.standard_normal(6)
            T_B_W = T_B_W @ _small_motion(wob[:3] * WOBBLE_MM, wob[3:] * WOBBLE_DEG)
        phi_hint = float(scene.phi_at(np.array([s + proc.look_ahead_mm]))[0])
        yield renderer.render(T_B_W, spec.t0_s + t, arc_on=k >= arc_on_frame,
                              laser_on=k not in spec.laser_off, phi_hint=phi_hint)



def simulate_labelled(cell: CellConfig, part: PartConfig, noise: NoiseConfig,
                      spec: SequenceSpec) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """A whole sequence of :func:`simulate` in memory, for benchmarks that score trackers.

    Returns:
        frames: the (H, W, 3) uint8 BGR frames; labels: (N, 2) true feature pixels (u, v);
        arc: (N,) bool, the arc burns (the frames a tracker is scored on).

    Example:
        >>> from torchseam.core.config import load_cell, load_part, load_noise
        >>> f, uv, arc = simulate_labelled(load_cell(), load_part(), load_noise(),
        ...                                SequenceSpec(n_frames=7))
        >>> len(f), uv.shape, int(arc.sum())
        (7, (7, 2), 2)
    """
    frames, labels, arc = [], [], []
    for img, truth in simulate(cell, part, noise, spec):
        frames.append(img)
        labels.append(truth.uv)
        arc.append(truth.arc_on)
    return frames, np.array(labels, dtype=float), np.array(arc, dtype=bool)


def _small_motion(dp_mm: np.ndarray, drot_deg: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    ang = np.linalg.norm(drot_deg)
    if ang > 0:
        T[:3, :3] = rotation_about(drot_deg / ang, np.deg2rad(ang))
    T[:3, 3] = dp_mm
    return T


def _background(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """Dim, blotchy metal seen through the band-pass filter, (H, W, 3) float32."""
    low = rng.random((h // 32 + 2, w // 32 + 2)).astype(np.float32)
    low = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    grey = BACKGROUND_GREY * (0.5 + low)
    return grey[..., None] * np.array([0.5, 0.6, 1.0], np.float32)
