"""EAKF-STC for one live stream (B = 1) in numpy: the inference twin of :class:`EAKFSTC`.

The torch module is what is fitted and what evaluates batches; at B = 1 on a CPU its ~800 tiny
tensor ops per frame cost more in dispatch (~2-3 ms) than in arithmetic. This twin runs the
same equations, with the same parameters read from a module, as ~120 numpy calls on (64, 64)
windows and one compiled kernel for the confidence map's peak and its quality
(:mod:`torchseam.track._kernels`; ~0.35 ms a frame in all), and it crops the red-stripe
response from the colour frame only where the windows lie instead of converting the whole
frame. It is inference only: no gradients, no
batch, the module's settings for live tracking (``crop="nearest"``, ``peak="subpixel"``, no
scale update); anything else is refused, not approximated.

Equivalence: in float64 it gives the module's points, statuses and quality scores to ~1e-9
(``tests/test_track_lite.py`` steps both through simulated heavy-arc frames, re-anchoring
included). The module runs in float32, so the twin's float64 answers differ from it by
rounding, which can flip a near-tie in the argmax on rare frames; the accuracy figures in
``docs/benchmarks.md`` are the twin's.

Example:
    >>> import numpy as np
    >>> trk = LiteEAKFSTC.from_module(EAKFSTC(window=(32, 32), target=(16, 16)))
    >>> f = np.zeros((96, 128), np.uint8); f[48, :] = 200; f[:, 64] = 200
    >>> trk.init(f, np.array([64.0, 48.0]))
    >>> uv, status, q = trk.step(f)
    >>> np.round(uv, 3).tolist(), status
    ([64.0, 48.0], 0)
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft
from torch import Tensor

from torchseam.core.checks import InputError
from torchseam.core.kernels import load_kernels
from torchseam.track.base import Tracker
from torchseam.track.fusion import EAKFSTC, TrackStatus
from torchseam.track.stc import confidence_map, weight_window
from torchseam.vision.tipm import red_response

__all__ = ["LiteEAKFSTC", "LiteTracker"]

_TINY = float(np.finfo(np.float64).tiny)


def _pocketfft():
    """pocketfft's transforms, which ``scipy.fft.rfft2`` / ``irfft2`` end in, to call without
    scipy's dispatch (~10 us of the ~20 us of a (64, 64) transform; two or three a frame), or
    None: used only when they give scipy.fft's numbers to the bit on a test array (scipy's
    private module may move)."""
    try:
        from scipy.fft._pocketfft import pypocketfft as pfft
        x = np.random.default_rng(0).normal(size=(8, 6))
        X = scipy.fft.rfft2(x)
        if (np.array_equal(pfft.r2c(x, (0, 1), True, 0, None, 1), X)
                and np.array_equal(pfft.c2r(1j * X + X, (0, 1), 6, False, 2, None, 1),
                                   scipy.fft.irfft2(1j * X + X, s=(8, 6)))):
            return pfft
    except Exception:  # noqa: BLE001 - any trouble: scipy.fft as it is
        pass
    return None


_PFFT = _pocketfft()


def _rfft2(x: np.ndarray) -> np.ndarray:
    """``scipy.fft.rfft2(x)`` of a (H, W) float64 array."""
    if _PFFT is None:
        return scipy.fft.rfft2(x)
    return _PFFT.r2c(np.ascontiguousarray(x, dtype=np.float64), (0, 1), True, 0, None, 1)


def _irfft2(X: np.ndarray, s: tuple[int, int]) -> np.ndarray:
    """``scipy.fft.irfft2(X, s=s)`` of a (H, W // 2 + 1) complex128 array."""
    if _PFFT is None:
        return scipy.fft.irfft2(X, s=s)
    return _PFFT.c2r(np.ascontiguousarray(X, dtype=np.complex128), (0, 1), int(s[1]), False, 2,
                     None, 1)


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


class LiteEAKFSTC:
    """B = 1 numpy EAKF-STC with the parameters of an :class:`EAKFSTC` module.

    Build with :meth:`from_module`. Frames are (H, W) grey or (H, W, 3) BGR uint8 (the grey
    image is then the red-stripe response ``R - max(G, B)``, computed per window). The state
    names follow :mod:`torchseam.track.eakf` and :mod:`torchseam.track.stc` without the
    batch dimension: ``x`` (2, 4), ``P`` (2, 4, 4), ``Z`` (2, 2), ``s`` (2, 2), ``s_ref`` (2,),
    ``H_f`` (H, W//2+1) complex.
    """

    def __init__(self, params: dict) -> None:
        self.h, self.w = params["window"]
        self.weight = params["weight"]            # (H, W) focus window w_sigma (eq. 5)
        self.conf_f = params["conf_f"]            # (H, W//2+1) rfft2 of c (eq. 1)
        self.rho, self.eps = params["rho"], params["eps"]
        self.reg = params.get("reg", 0.0)         # > 0: eq. 8 regularised (Wiener)
        self.anchor = params.get("anchor", 0.0)   # weight of the start model in detection
        self.anchor_frames = params.get("anchor_frames", 1)
        self.H_ref: np.ndarray | None = None
        self.exclude = params["exclude"]
        self.Phi, self.GQG = params["Phi"], params["GQG"]          # (2, 4, 4)
        self.H_star, self.R, self.psi = params["H_star"], params["R"], params["psi"]
        self.p0 = params["p0"]                    # (2, 4)
        self.c = params["guard"]                  # (13,) DriftGuard.constants()
        self.max_coast, self.lost_std = params["max_coast"], params["lost_std"]
        h, w = self.h, self.w
        # the fourier_shift phase ramps' angular frequencies (rows, half-spectrum columns)
        self._fy = np.fft.fftfreq(h) * (-2.0 * math.pi)
        self._fx = np.fft.rfftfreq(w) * (-2.0 * math.pi)
        self._ar_h = np.arange(h) - h // 2
        self._ar_w = np.arange(w) - w // 2
        self._e = max(self.exclude, 1)  # the peak's area left out of the sidelobe: +-e
        self._even = not (h % 2 or w % 2)  # competing peaks on 2x2-block maxima (see stc.py)
        self._eb = (self.exclude + 1) // 2 if self._even else self.exclude
        self.H_f: np.ndarray | None = None
        self.frame = 0
        # (frame id, crop centre) and the prior spectrum of the last window: the learning step
        # re-crops at the filtered point, usually the pixel it detected at. Valid within one
        # step only (frame ids are reused): cleared when a step or re-anchoring ends.
        self._last_prior: tuple[tuple[int, int, int], np.ndarray] | None = None
        # learning steps not applied yet (see idle): (window or None, its prior spectrum or
        # None, centre, rho scale), in order
        self._pending: list[tuple[np.ndarray | None, np.ndarray | None, np.ndarray, float]] = []
        # numba: compiled (or loaded) now, not on the first frame
        self._peak_quality = load_kernels(__package__).peak_quality
        # the filter's state, set by init (with H_f: None until then)
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.Z: np.ndarray | None = None
        self.s: np.ndarray | None = None
        self.s_ref: np.ndarray | None = None
        self.x_post: np.ndarray | None = None
        self.coast = 0
        self.status = int(TrackStatus.TRACKED)

    @classmethod
    def from_module(cls, module: EAKFSTC) -> LiteEAKFSTC:
        """Read the natural parameters of ``module`` (any dtype or device) once."""
        cfg = module.config
        stc = module.stc
        if stc.crop != "nearest" or stc.peak != "subpixel" or stc.scale_update:
            raise InputError(
                f"LiteEAKFSTC runs crop='nearest', peak='subpixel' without the scale update; "
                f"this module has crop={stc.crop!r}, peak={stc.peak!r}, "
                f"scale_update={stc.scale_update} (use the torch module)")

        def npy(t: Tensor) -> np.ndarray:
            return t.detach().to("cpu").double().numpy()

        import torch  # the module's parameters are tensors; the twin's state is not

        with torch.no_grad():
            m = module.eakf.matrices()
            weight = weight_window(stc.window_size, stc.sigma.detach().double())
            conf = confidence_map(stc.window_size, stc.alpha.detach().double(),
                                  stc.beta.detach().double())
            return cls({
                "window": stc.window_size, "weight": npy(weight),
                "conf_f": np.fft.rfft2(npy(conf)), "rho": float(stc.rho), "eps": stc.eps,
                "exclude": stc.exclude, "reg": float(stc.reg), "anchor": float(stc.anchor),
                "anchor_frames": stc.anchor_frames, "Phi": npy(m.Phi), "GQG": npy(m.GQG),
                "H_star": npy(m.H_star), "R": npy(m.R), "psi": npy(m.psi),
                "p0": npy(module.eakf.p0).reshape(2, 4) * np.ones((2, 1)),
                "guard": npy(module.guard.constants()), "max_coast": cfg.max_coast,
                "lost_std": cfg.lost_std})

    # ------------------------------------------------------------------ windows
    @staticmethod
    def _frame(frame: np.ndarray) -> np.ndarray:
        if not isinstance(frame, np.ndarray) or not (
                frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)):
            raise InputError(
                f"frame: expected an (H, W) grey or (H, W, 3) BGR array, got "
                f"{type(frame).__name__} {getattr(frame, 'shape', '')}")
        return frame

    def _window(self, frame: np.ndarray, c: np.ndarray) -> np.ndarray:
        """(H, W) float64 grey window whose index (H//2, W//2) is pixel c (2,) int (u, v);
        border pixels replicated (``extract_windows`` in ``nearest`` mode)."""
        hi, wi = frame.shape[:2]
        u, v = int(c[0]), int(c[1])
        r0, c0 = v - self.h // 2, u - self.w // 2
        if r0 >= 0 and c0 >= 0 and r0 + self.h <= hi and c0 + self.w <= wi:
            win = frame[r0:r0 + self.h, c0:c0 + self.w]
        else:
            rows = np.clip(v + self._ar_h, 0, hi - 1)
            cols = np.clip(u + self._ar_w, 0, wi - 1)
            win = frame[rows[:, None], cols[None, :]]
        if win.ndim == 3:
            win = red_response(np.ascontiguousarray(win))
        return win.astype(np.float64)

    def _prior_f(self, frame: np.ndarray, c: np.ndarray) -> np.ndarray:
        key = (id(frame), int(c[0]), int(c[1]))
        if self._last_prior is not None and self._last_prior[0] == key:
            return self._last_prior[1]  # learning where it detected: the very same window
        prior_f = self._spectrum(self._window(frame, c))
        self._last_prior = (key, prior_f)
        return prior_f

    def _spectrum(self, win: np.ndarray) -> np.ndarray:
        return _rfft2((win - win.mean()) * self.weight)  # eq. 4-5 (context_prior)

    # ------------------------------------------------------------------ STC
    def _learn(self, frame: np.ndarray, centre: np.ndarray, rho_scale: float) -> None:
        """Eq. 8-9 at ``centre`` (STC.learn), applied by :meth:`idle` or the next step: only
        the window is cut now (the caller may reuse the frame's buffer)."""
        r = np.floor(centre + 0.5)
        key = (id(frame), int(r[0]), int(r[1]))
        centre = np.array(centre, dtype=float)
        if self._last_prior is not None and self._last_prior[0] == key:
            self._pending.append((None, self._last_prior[1], centre, rho_scale))
        else:
            self._pending.append((self._window(frame, r), None, centre, rho_scale))

    def idle(self) -> None:
        """Apply the learning left from the last step or re-anchoring (the context model the
        next frame is searched with). :meth:`step` does it first if nobody did; the live loop
        calls this between frames, after its command is out, where it costs nothing on the
        frame -> command path. Same numbers either way."""
        pending, self._pending = self._pending, []
        for win, prior_f, centre, rho_scale in pending:
            if prior_f is None:
                assert win is not None  # a step queues its window or its prior spectrum
                prior_f = self._spectrum(win)
            self._apply_learn(prior_f, centre, rho_scale)

    def _apply_learn(self, prior_f: np.ndarray, centre: np.ndarray, rho_scale: float) -> None:
        r = np.floor(centre + 0.5)
        d = centre - r  # the target's sub-pixel place in the integer crop (fourier_shift)
        ramp = np.exp(1j * (d[1] * self._fy))[:, None] * np.exp(1j * (d[0] * self._fx))[None]
        if self.reg > 0:  # learn_spatial_context_reg
            power = prior_f.real * prior_f.real + prior_f.imag * prior_f.imag
            h_f = (self.conf_f * ramp) * np.conj(prior_f) / (power + power.mean() * self.reg
                                                              + self.eps)
        else:
            h_f = (self.conf_f * ramp) / (prior_f + self.eps) if self.eps else \
                (self.conf_f * ramp) / prior_f
        self.frame += 1
        if self.frame == 1:
            self.H_f = h_f
        else:
            self.H_f = self.H_f + (self.rho * rho_scale) * (h_f - self.H_f)
        if self.anchor > 0 and self.frame <= self.anchor_frames:  # the start model
            self.H_ref = self.H_f if self.frame == 1 else \
                self.H_ref + (self.H_f - self.H_ref) / self.frame

    def _detect(self, frame: np.ndarray, centre: np.ndarray
                ) -> tuple[np.ndarray, float, float, int, float]:
        """Eq. 10-11 around ``centre``: (uv, psr, second_ratio, n_peaks, peak)."""
        base = np.floor(centre + 0.5)
        H_f = self.H_f
        if self.anchor > 0 and self.H_ref is not None:
            H_f = H_f + self.anchor * (self.H_ref - H_f)
        resp = _irfft2(H_f * self._prior_f(frame, base), (self.h, self.w))
        off_u, off_v, peak, psr, second_ratio, n_peaks = self._peak_quality(
            resp, self._e, self._even, self._eb)
        off = np.array([off_u, off_v])
        return base + off, psr, second_ratio, n_peaks, peak

    # ------------------------------------------------------------------ API
    def init(self, frame: np.ndarray, uv0: np.ndarray) -> None:
        """Start at ``uv0`` (2,) in ``frame`` (EAKFSTC.init_state)."""
        frame = self._frame(frame)
        hi, wi = frame.shape[:2]
        uv0 = np.asarray(uv0, float).reshape(-1)
        if uv0.shape != (2,) or not np.all(np.isfinite(uv0)) or not (
                -0.5 <= uv0[0] <= wi - 0.5 and -0.5 <= uv0[1] <= hi - 0.5):
            raise InputError(f"uv0: the start (u, v) = {uv0.tolist()} is not a point "
                             f"inside the {wi} x {hi} frame")
        self.x = np.stack([uv0, np.zeros(2), uv0, np.zeros(2)], axis=-1)  # eakf_init
        self.P = np.zeros((2, 4, 4))
        self.P[:, range(4), range(4)] = self.p0
        self.Z = np.stack([uv0, np.zeros(2)], axis=-1)
        self.s = np.array([[1.0, 1e6], [1.0, 1e6]])  # UNKNOWN_SCALE on the first displacement
        self.s_ref = np.ones(2)
        self.x_post = None
        self.H_f, self.H_ref, self.frame = None, None, 0
        self._last_prior = None
        self._pending = []
        self._learn(frame, uv0, 1.0)
        self._last_prior = None
        self.idle()
        self.coast, self.status = 0, int(TrackStatus.TRACKED)

    @property
    def uv(self) -> np.ndarray:
        """(2,) position estimate at the newest frame."""
        if self.x is None:
            raise InputError("LiteEAKFSTC.uv: call init(frame, uv0) first")
        return self.x[:, 0].copy()

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, int, dict[str, float | np.ndarray]]:
        """One EAKF-STC step (EAKFSTC.step_state): (uv (2,), status, quality)."""
        if self.H_f is None:
            raise InputError("LiteEAKFSTC.step: call init(frame, uv0) first")
        assert (self.x is not None and self.P is not None and self.Z is not None
                and self.s is not None and self.s_ref is not None)  # set by init, with H_f
        frame = self._frame(frame)
        self.idle()  # the last step's learning, if nobody applied it between frames
        hi, wi = frame.shape[:2]
        Phi, x, P = self.Phi, self.x, self.P
        pred = (Phi[:, 0, :] * x).sum(axis=-1)                             # 1. prediction
        centre = np.minimum(np.maximum(pred, 0.0), [wi - 1.0, hi - 1.0])
        z, psr, second_ratio, n_peaks, peak = self._detect(frame, centre)  # 2. measurement
        # 3. innovation of the delayed update (eakf_innovation, eq. 21-25)
        Z_new = np.stack([z, z - self.Z[:, 0]], axis=-1)
        nu = Z_new - self.psi * self.Z - (self.H_star @ x[..., None])[..., 0]
        PHt = P @ self.H_star.transpose(0, 2, 1)
        HPHt = self.H_star @ PHt
        noise = self.psi ** 2 * (self.s - 1.0)
        s_gate = np.stack([np.ones(2), np.maximum(self.s_ref, 1.0)], axis=-1)
        S_pos = HPHt[:, 0, 0] + self.R[:, 0] * (s_gate[:, 0] + noise[:, 0])
        d2 = float((nu[:, 0] ** 2 / S_pos).sum())
        spread = max(float(S_pos.prod()), 0.0) ** 0.25
        # 4. drift guard (DriftGuard.forward)
        c = self.c
        l_psr = c[0] * (math.log(max(psr, _TINY)) - c[1])
        l_sec = c[2] * (c[3] - second_ratio)
        l_gate = c[4] * (c[5] - math.sqrt(d2 + 1e-12)) - c[6] * (math.log(max(spread, _TINY))
                                                                 - c[7])
        trust = _sigmoid(l_psr) * _sigmoid(l_sec) * _sigmoid(l_gate)
        r_scale = math.exp(c[8] * _sigmoid(c[11] * (c[12] - trust)))
        rho_scale = _sigmoid(c[9] * (trust - c[10]))
        # 5. update (eakf_update, eq. 25-26), the kept measurement blended by trust
        sc = np.full(2, r_scale)
        s_new = np.stack([sc, np.maximum(sc, self.s_ref)], axis=-1)
        S = HPHt.copy()
        S[:, [0, 1], [0, 1]] += self.R * (s_new + noise)
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        S_inv = np.stack([np.stack([S[:, 1, 1], -S[:, 0, 1]], -1),
                          np.stack([-S[:, 1, 0], S[:, 0, 0]], -1)], -2) / det[:, None, None]
        K = PHt @ S_inv
        x_post = x + (K @ nu[..., None])[..., 0]
        P_post = P - K @ PHt.transpose(0, 2, 1)
        self.x = (Phi @ x_post[..., None])[..., 0]
        P = Phi @ P_post @ Phi.transpose(0, 2, 1) + self.GQG
        self.P = 0.5 * (P + P.transpose(0, 2, 1))
        drop = 1.0 - trust
        self.Z = Z_new - drop * nu
        self.s = s_new - drop * (s_new - 1.0)
        self.s_ref = sc
        self.x_post = x_post
        uv = self.x[:, 0].copy()
        self._learn(frame, uv, rho_scale)                                  # 6. re-centre, learn
        self._last_prior = None
        std = math.sqrt(max(float(self.P[:, 0, 0].max()), 0.0))           # 7. status
        distrusted = int(trust < 0.5)
        self.coast = (self.coast + 1) * distrusted
        lost = self.coast > self.max_coast or std > self.lost_std
        self.status = int(TrackStatus.LOST) if lost else distrusted
        return uv, self.status, {"z": z, "trust": trust, "psr": psr,
                                 "second_ratio": second_ratio, "n_peaks": n_peaks,
                                 "peak": peak, "d2": d2, "r_scale": r_scale,
                                 "rho_scale": rho_scale, "std": std}

    def reanchor(self, frame: np.ndarray, uv: np.ndarray, rate: float = 1.0) -> None:
        """Move onto an absolute fix ``uv`` (2,) of the newest frame (EAKFSTC.reanchor)."""
        if self.H_f is None:
            raise InputError("LiteEAKFSTC.reanchor: call init(frame, uv0) first")
        assert self.x is not None and self.Z is not None  # set by init, with H_f
        frame = self._frame(frame)  # every check before the state moves
        uv = np.asarray(uv, float).reshape(-1)
        if uv.shape != (2,) or not np.all(np.isfinite(uv)):
            raise InputError(f"reanchor: uv must be 2 finite numbers, got {uv.tolist()}")
        d = uv - self.x[:, 0]
        for a in (self.x, self.x_post):
            if a is not None:
                a[:, 0] += d   # u(k) and u(k-1) together: the velocity is kept
                a[:, 2] += d
        self.Z[:, 0] += d
        self._last_prior = None  # a fix may come on a frame other than the last step's
        self._learn(frame, uv, rate / self.rho)
        self._last_prior = None
        self.coast, self.status = 0, int(TrackStatus.TRACKED)


class LiteTracker(Tracker):
    """EAKF-STC for one stream: the fitted module's parameters run by its numpy twin
    :class:`~torchseam.track.lite.LiteEAKFSTC` (same equations, a third of the time at B = 1,
    where the module's tensor-op dispatch dominates)."""

    name = "eakf-stc"

    def __init__(self, module: EAKFSTC) -> None:
        self.lite = LiteEAKFSTC.from_module(module)
        self.fitted_fps = module.eakf.frame_rate

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.lite.init(frame, uv)

    def reanchor(self, frame: np.ndarray, uv: np.ndarray) -> None:
        """Move EAKF-STC onto an absolute fix ``uv`` of this (the newest) frame."""
        self.lite.reanchor(frame, uv)

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        uv, status, _ = self.lite.step(frame)
        return uv, status

    def idle(self) -> None:
        """Between frames: the context learning of the last update (see LiteEAKFSTC.idle)."""
        self.lite.idle()
