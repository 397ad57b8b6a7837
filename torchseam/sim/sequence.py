"""Sequences of simulated frames: the sensor rides along the seam at weld speed and frame rate.

The robot follows the *nominal* (design) seam with a small path wobble, while the true part
deviates from the design; so the feature point wanders in the image the way it does in a real
cell. Every frame carries its ground truth (:class:`FrameTruth`).

The appearance family (``families:`` in ``configs/noise.yaml``) sets how the frame looks:
stripe cross-section and colour, glare and spatter shapes, the arc's specular glint on the
main pipe, fume, motion blur and the camera's exposure and response. It never changes the
geometry, so the labels are the same in every family.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from torchseam.core.config import AppearanceFamily, CellConfig, NoiseConfig, PartConfig
from torchseam.core.kernels import load_kernels
from torchseam.core.transforms import apply, invert, rotation_about
from torchseam.sim.noise import ARC_BGR, SPATTER_BGR, STRIPE_BGR, ArcNoise, NoiseFlags
from torchseam.sim.scene import Scene
from torchseam.sim.sensor import LaserSensor

BACKGROUND_GREY = 6.0       # ambient light behind the band-pass filter
WOBBLE_MM = 0.15            # robot path wobble (std, smooth)
WOBBLE_DEG = 0.15
ARC_LIFT_MM = 3.0           # the arc's light centre above the torch tip, along the torch axis
FLASH_GREY = 400.0          # an injected arc flash (fault): grey levels in its weakest channel
# (B, G, R) <- (stripe, glare, spatter) grey layers of the ``sim`` family
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
    family: str | None = None         # appearance family (None: the noise config's default)


class SensorRenderer:
    """Renders what the sensor sees from any torch pose: the frame and its ground truth.

    The arc-noise state (flicker, bursts, reflections) carries over calls, so successive calls
    form a sequence. :func:`simulate` drives it along the nominal path; the closed-loop demo
    drives it from wherever the simulated robot actually is.

    Args:
        scene: the part (true and nominal) on its positioner.
        level: arc-noise level in [0, MAX_NOISE_LEVEL] (1: heavy); seed: random seed.
        family: appearance family, a name of ``noise.families`` (None: ``noise.family``);
            ValueError naming an unknown one.
    """

    def __init__(self, cell: CellConfig, scene: Scene, noise: NoiseConfig, level: float,
                 seed: int, family: str | None = None) -> None:
        self.cell, self.scene = cell, scene
        self.look = look = noise.appearance(family)
        self.rng = np.random.default_rng(seed)
        self.sensor = LaserSensor(cell)
        w, h = cell.camera.width, cell.camera.height
        self.size = (w, h)
        self.arc_noise = ArcNoise(noise, level, (w, h), int(self.rng.integers(2**31)), look)
        self.clean = ArcNoise(noise, 0.0, (w, h), 0, look)
        self.sigma_clean = noise.sensor.sigma_clean
        self.mix = _colour_mix(look)
        ex = look.exposure
        # the camera stage runs only when the family has something for it to do
        self._camera_on = (look.motion_blur_px > 1 or ex.gain != 1.0 or ex.gamma != 1.0
                           or any(ex.bleed) or ex.band_prob > 0)
        self._blur = _motion_kernel(look.motion_blur_px)
        self.background = _background(self.rng, w, h)
        self.read_noise = [self.rng.standard_normal((h + 16, w + 16, 3), dtype=np.float32)
                           for _ in range(4)]
        self._bufs: dict[tuple[str, int], np.ndarray] = {}
        self._k = load_kernels(__package__)  # compiled (or loaded) now, not on the first frame
        # and the part's ray casts (their kernels load on the first cast: seconds on a fresh
        # install, which a virtual camera's first frame would pay): one ray now
        scene.true_joint.raycast(np.zeros(3), np.array([[0.0, 0.0, 1.0]]))
        # the colour mix and the last pass in one compiled pass where that is cv2.transform's
        # arithmetic (see _fused_mix_agrees); the camera stage works between the two
        self._fused = not self._camera_on and _fused_mix_agrees(self.mix, w, h)
        self._tail_from = _mix_tail_from(w * h)
        self._tool_inv = invert(cell.tool.matrix())   # camera_pose's factors
        self._hand_eye = cell.hand_eye.matrix()
        self.k = 0

    def _buf(self, name: str, channels: int, zero: bool = False) -> np.ndarray:
        """A reused float32 (H, W, channels) plane of this renderer (``zero``: all zeros)."""
        key = (name, channels)
        buf = self._bufs.get(key)
        if buf is None:
            w, h = self.size
            buf = self._bufs[key] = (np.zeros if zero else np.empty)((h, w, channels),
                                                                      np.float32)
        return buf

    def render(self, T_B_W: np.ndarray, t_s: float, arc_on: bool = True, laser_on: bool = True,
               phi_hint: float | None = None, force_flash: bool = False,
               exposure: float = 1.0) -> tuple[np.ndarray, FrameTruth]:
        """Frame (H, W, 3) uint8 and truth with the torch at ``T_B_W`` at weld time ``t_s``.

        ``phi_hint``: branch angle near the stripe (default: from the torch position).
        ``force_flash``: blind the sensor with an arc flash this frame (fault injection).
        ``exposure``: the camera's exposure as a share of the family's (> 0): it scales all
        light (stripe, arc, background) before the sensor clips, as the family's
        ``exposure.gain`` does; the read noise is the sensor's and stays. The random draws
        are the same at any exposure, so one sequence can be rendered at several.
        """
        if not exposure > 0.0:
            raise ValueError(f"exposure must be > 0, got {exposure}")
        scene, sensor, rng = self.scene, self.sensor, self.rng
        w, h = self.size
        # sensor.camera_pose's product, its factors made once (the same numbers)
        T_B_C = T_B_W @ self._tool_inv @ self._hand_eye
        T_B_T = scene.part_pose(t_s)
        T_T_C = invert(T_B_T) @ T_B_C
        if phi_hint is None:
            p_T = apply(invert(T_B_T), T_B_W[:3, 3])
            phi_hint = scene.true_joint.phi_near(p_T)
        view = sensor.view(scene.true_joint, T_T_C, phi_hint)
        # the arc burns at the torch tip
        arc_uv = sensor.project(apply(invert(T_B_C), T_B_W[:3, 3])[None])[0]
        src = self.arc_noise if arc_on else self.clean
        centre = np.array([w / 2.0, h / 2.0])
        # (the noise's own planes: this frame is done with them before the next call)
        layers = src.next(arc_uv, view.seam_uv if np.all(np.isfinite(view.seam_uv)) else centre,
                          reuse=True)
        look = self.look
        if arc_on and look.glare.glint > 0 and src.level > 0:
            # the arc mirrored by the main pipe: a specular band along the pipe (no random draw)
            light = apply(invert(T_B_T), T_B_W[:3, 3] - ARC_LIFT_MM * T_B_W[:3, 2])
            gain = look.glare.glint * src.cfg.glare.peak * src.level * src.flicker
            layers.glare += np.float32(gain) * sensor.arc_glint(scene.true_joint, T_T_C, light)
        if force_flash:
            # light enough to clip the glare's weakest channel after the exposure: blinded
            # in every response (the red excess and the brightness alike)
            layers.glare += np.float32(
                FLASH_GREY / (min(look.glare.bgr) * look.exposure.gain * exposure))
            layers.flags.flash = True
        stripe = (sensor.stripe_layer(view, rng, layers.gaps, look.stripe,
                                      out=self._buf("stripe", 1)[..., 0]) if laser_on
                  else np.zeros((h, w), np.float32))
        chans = [stripe, layers.glare, layers.spatter]
        if look.haze.amount > 0:   # fume: hides part of the stripe, adds a grey veil
            haze = layers.haze if layers.haze is not None else np.zeros((h, w), np.float32)
            if layers.haze is not None and look.haze.absorb > 0:
                stripe *= 1.0 - look.haze.absorb * haze
            chans.append(haze)
        camera_on = self._camera_on or exposure != 1.0
        fused = self._fused and len(chans) == 3 and not camera_on
        if not fused:
            # colour mixing of stripe, arc glare, spatter (and fume) light in one pass, into
            # reused planes (frame-sized temporaries cost page faults on every frame)
            img: np.ndarray = cv2.transform(cv2.merge(chans, self._buf("merged", len(chans))),
                                            self.mix, self._buf("light", 3))
        dy, dx = rng.integers(0, 16, 2)
        sigma = src.sensor_sigma() if arc_on else self.sigma_clean
        if look.read_noise > 0:   # independent extra noise: adds in quadrature
            sigma = float(np.hypot(sigma, look.read_noise))
        frame = np.empty((h, w, 3), np.uint8)
        noise = self.read_noise[self.k % 4]
        if fused:
            # the colour mix and the last pass below in one compiled pass (the numbers of
            # cv2.transform and finish_frame to the bit: torchseam.sim._kernels.mix_finish)
            c = np.ascontiguousarray
            self._k.mix_finish(c(stripe), c(layers.glare), c(layers.spatter), self.mix,
                               self._tail_from, self.background.reshape(h, -1),
                               noise.reshape(len(noise), -1),
                               int(dy), int(dx) * 3, np.float32(sigma), frame.reshape(h, -1))
        elif camera_on:
            img += self.background
            img = self._camera(img, layers.rows, exposure)
            # the background is in the light already: add nothing more
            background = self._buf("zero", 3, zero=True)
        else:
            background = self.background
        if not fused:
            # light + background + sigma * read noise, clipped and cast: one compiled pass,
            # the numbers of numpy's passes to the bit (torchseam.sim._kernels.finish_frame)
            self._k.finish_frame(np.ascontiguousarray(img).reshape(h, -1),
                                 background.reshape(h, -1), noise.reshape(len(noise), -1),
                                 int(dy), int(dx) * 3, np.float32(sigma), frame.reshape(h, -1))
        truth = FrameTruth(
            index=self.k, t_s=t_s, uv=view.seam_uv, visible=view.visible and laser_on,
            laser_on=laser_on, arc_on=arc_on, seam_B=apply(T_B_T, view.seam_T),
            arm_B=apply(T_B_T, view.arm_T), arm_uv=view.arm_uv, T_B_C=T_B_C, T_B_W=T_B_W,
            arc_uv=arc_uv, flags=layers.flags)
        self.k += 1
        return frame, truth

    def _camera(self, img: np.ndarray, rows: np.ndarray | None, exposure: float = 1.0
                ) -> np.ndarray:
        """The family's optics and camera on the (H, W, 3) float32 light: horizontal motion
        blur, exposure gain (the family's times ``exposure``, and a rolling-shutter band's
        ``rows`` gain), red overflow bleeding into green and blue, then the response curve."""
        ex = self.look.exposure
        if self._blur is not None:
            img = cv2.filter2D(img, -1, self._blur, borderType=cv2.BORDER_REFLECT)
        gain = ex.gain * exposure
        if gain != 1.0:
            img *= np.float32(gain)
        if rows is not None:
            img *= rows[:, None, None]
        if any(ex.bleed):
            over = np.maximum(img[..., 2] - 255.0, 0.0)
            img[..., 0] += np.float32(ex.bleed[0]) * over
            img[..., 1] += np.float32(ex.bleed[1]) * over
        if ex.gamma != 1.0:
            np.maximum(img, 0.0, out=img)
            img *= np.float32(1 / 255)
            np.power(img, np.float32(ex.gamma), out=img)
            img *= np.float32(255)
        return img


def simulate(cell: CellConfig, part: PartConfig, noise: NoiseConfig, spec: SequenceSpec,
             exposure: Callable[[int], float] | None = None
             ) -> Iterator[tuple[np.ndarray, FrameTruth]]:
    """Yield ``(frame, truth)`` pairs: (H, W, 3) uint8 BGR frames with their ground truth.

    The robot runs the nominal path at weld speed (with a small wobble). The first
    ``noise.clean_lead_frames`` frames (or up to ``spec.arc_on_frame``) are arc-off (clean),
    as before a real weld starts; then the arc noise of ``spec.level`` applies.

    ``exposure``: called with ``k`` just before frame ``k`` is rendered (the frames before it
    already yielded), it gives that frame's exposure as a share of the family's (see
    :meth:`SensorRenderer.render`): an automatic exposure in the loop. None: the family's.

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
    renderer = SensorRenderer(cell, scene, noise, spec.level, int(rng.integers(2**31)),
                              family=spec.family)
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
                              laser_on=k not in spec.laser_off, phi_hint=phi_hint,
                              exposure=1.0 if exposure is None else float(exposure(k)))



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


_FUSED_AGREES: dict[tuple[bytes, int, int], bool] = {}


def _mix_tail_from(n_pixels: int) -> int:
    """The first pixel that ``cv2.transform`` (3 x 3, float32, AVX2) computes in its scalar
    loop, of a continuous image of ``n_pixels``: the last 4 to 11 (found by trying; checked
    on the frame's own size by :func:`_fused_mix_agrees`)."""
    return max(0, 8 * ((n_pixels - 5) // 8) + 4)


def _fused_mix_agrees(mix: np.ndarray, w: int, h: int) -> bool:
    """Whether ``_kernels.mix_finish`` makes the (h, w) frame that ``cv2.transform`` (of the
    merged layers by ``mix``) and ``_kernels.finish_frame`` make, to the bit, on this machine:
    its light (``_kernels.mix_light``, the same arithmetic) against ``cv2.transform``'s on
    random layers of that size (zeros, faint and bright light), and the frames; tried once per
    matrix and size (a few ms). The kernel computes what OpenCV's AVX2 path does (fused
    multiply-adds); an OpenCV without it (another CPU, another build) rounds differently, and
    there the renderer makes the two calls."""
    key = (mix.tobytes(), w, h)
    ok = _FUSED_AGREES.get(key)
    if ok is None:
        k = load_kernels(__package__)
        rng = np.random.default_rng(5)
        layers = [(rng.random((h, w), dtype=np.float32) * 600.0).astype(np.float32)
                  for _ in range(3)]
        for i, layer in enumerate(layers):
            layer[rng.random((h, w)) < 0.3] = 0.0
            layer[i::3, ::5] *= np.float32(1e-3)
        m32 = np.ascontiguousarray(mix, dtype=np.float32)
        tail = _mix_tail_from(w * h)
        mixed = cv2.transform(cv2.merge(layers), mix)
        light = np.empty((h, 3 * w), np.float32)
        k.mix_light(*layers, m32, tail, light)
        bg = (rng.random((h, 3 * w), dtype=np.float32) * 9.0).astype(np.float32)
        noise = rng.standard_normal((h + 2, 3 * (w + 2)), dtype=np.float32)
        a, b = np.empty((h, 3 * w), np.uint8), np.empty((h, 3 * w), np.uint8)
        sigma = np.float32(3.3)
        k.finish_frame(np.ascontiguousarray(mixed).reshape(h, -1), bg, noise, 1, 3, sigma, a)
        k.mix_finish(*layers, m32, tail, bg, noise, 1, 3, sigma, b)
        ok = _FUSED_AGREES[key] = bool(np.array_equal(light, mixed.reshape(h, -1))
                                       and np.array_equal(a, b))
    return ok


def _small_motion(dp_mm: np.ndarray, drot_deg: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    ang = np.linalg.norm(drot_deg)
    if ang > 0:
        T[:3, :3] = rotation_about(drot_deg / ang, np.deg2rad(ang))
    T[:3, 3] = dp_mm
    return T


def _colour_mix(look: AppearanceFamily) -> np.ndarray:
    """(3, 3) float32 matrix (B, G, R) <- (stripe, glare, spatter); (3, 4) with the fume's grey
    as a fourth layer when the family has fume."""
    cols = [look.stripe.bgr, look.glare.bgr, look.spatter.bgr]
    if look.haze.amount > 0:
        cols.append((look.haze.amount,) * 3)
    return np.stack([np.asarray(c, np.float32) for c in cols], axis=1).astype(np.float32)


def _motion_kernel(length_px: int) -> np.ndarray | None:
    """(1, n) float32 horizontal box kernel of ``length_px`` centred on the pixel (an even
    length gets half-weight end taps), or None for no blur."""
    if length_px <= 1:
        return None
    taps = np.ones(length_px + 1 - length_px % 2, np.float32)
    if length_px % 2 == 0:
        taps[[0, -1]] = 0.5
    return (taps / length_px)[None, :]


def _background(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """Dim, blotchy metal seen through the band-pass filter, (H, W, 3) float32."""
    low = rng.random((h // 32 + 2, w // 32 + 2)).astype(np.float32)
    smooth: np.ndarray = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    grey = BACKGROUND_GREY * (0.5 + smooth)
    return grey[..., None] * np.array([0.5, 0.6, 1.0], np.float32)
