"""A camera like a real one: what happens to a frame between the ideal render and the socket.

Pure logic (numpy/OpenCV only; every call takes the time explicitly, no clocks or sockets), so
the runtime (``sim_bridge.app``) owns the I/O and the tests drive it step by step:

* :class:`CameraTiming`: per captured frame, whether it is dropped, when it is delivered
  (capture + latency +- jitter, in order) and the stamp its header carries (capture time on
  the autopilot's clock when hardware-synced, else on the camera's own clock).
* :class:`Sensor`: the photometric chain applied to a rendered frame: slow brightness
  (exposure/gain) drift, then shot noise (variance = conversion gain x signal) and read noise,
  rounded and saturated to 8 bits.
* :func:`line_kernel`: the motion-blur kernel of a straight image motion over the exposure
  (the geometry that produces the motion is the renderer's, ``sim_bridge.camera.camera``).

Each effect draws from its own seeded stream (``numpy.random.SeedSequence(seed).spawn``), so
switching one effect on or off does not change the others' realisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sim_bridge.config import CameraModelConfig
from sim_bridge.delay import rngs

__all__ = ["CameraTiming", "Capture", "Sensor", "line_kernel"]

_NOISE_BANK = 3
_NOISE_PAD = 64

@dataclass(frozen=True)
class Capture:
    """What happens to the frame exposed around ``t_capture_s`` (simulation time, s).

    ``dropped``: never delivered. ``deliver_s``: when it leaves on the frame socket (same
    clock). ``stamp_us``: the header's ``t_us`` (autopilot or camera clock, see
    :class:`CameraTiming`).
    """

    t_capture_s: float
    dropped: bool
    deliver_s: float
    stamp_us: int

    @property
    def latency_s(self) -> float:
        return self.deliver_s - self.t_capture_s


class CameraTiming:
    """Drops, latency and timestamps of the frames (``CameraModelConfig``)."""

    def __init__(self, cfg: CameraModelConfig, seed: int, clock_offset_s: float = 0.0) -> None:
        self.cfg = cfg
        self.clock_offset_s = clock_offset_s  # autopilot clock = simulation time + this
        self._drop_rng, self._lat_rng = rngs(seed, 2, salt=1)
        self._last_deliver_s = -math.inf

    def stamp_us(self, t_capture_s: float) -> int:
        """The header stamp of a frame captured at simulation time ``t_capture_s``: the
        autopilot's clock (``+ clock_offset_s``), or the camera's own clock derived from it."""
        c = self.cfg
        t_capture_s = t_capture_s + self.clock_offset_s
        if c.timestamp_clock == "camera":
            t = t_capture_s * (1.0 + c.clock_drift_ppm * 1e-6) + c.clock_offset_ms * 1e-3
        else:
            t = t_capture_s
        return max(0, round(t * 1e6))

    def capture(self, t_capture_s: float) -> Capture:
        c = self.cfg
        # both draws every frame so each stream stays aligned with the frame index
        dropped = bool(self._drop_rng.random() < c.drop_probability)
        jitter = self._lat_rng.uniform(-1.0, 1.0) * c.latency_jitter_ms
        latency_s = max(0.0, c.latency_ms + jitter) * 1e-3
        deliver = t_capture_s + latency_s
        if not dropped:
            deliver = max(deliver, self._last_deliver_s)  # in order, like a real pipeline
            self._last_deliver_s = deliver
        return Capture(t_capture_s, dropped, deliver, self.stamp_us(t_capture_s))


def line_kernel(dx_px: float, dy_px: float) -> np.ndarray | None:
    """Normalised float32 kernel of a straight motion by ``(dx, dy)`` pixels (col, row) during
    the exposure, centred (the blurred edge's 50 % level stays at the exposure middle); ``None``
    below half a pixel. The segment is sampled 8 times per pixel, each sample splatted
    bilinearly, so the kernel's centroid is exactly its centre and its spread that of the
    segment (a box of the motion's length, softened by less than a pixel)."""
    length = math.hypot(dx_px, dy_px)
    if length < 0.5:
        return None
    half = math.ceil(max(abs(dx_px), abs(dy_px)) / 2.0) + 1
    n = 2 * half + 1
    s = np.linspace(-0.5, 0.5, max(2, math.ceil(8 * length) + 1))
    x, y = half + s * dx_px, half + s * dy_px
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    k = np.zeros((n, n), np.float64)
    np.add.at(k, (y0, x0), (1 - fx) * (1 - fy))
    np.add.at(k, (y0, x0 + 1), fx * (1 - fy))
    np.add.at(k, (y0 + 1, x0), (1 - fx) * fy)
    np.add.at(k, (y0 + 1, x0 + 1), fx * fy)
    k /= k.sum()
    return k.astype(np.float32)


class Sensor:
    """Photometric chain of a mono8 sensor: brightness drift, shot + read noise, 8-bit rounding.

    The brightness gain is ``exp(x)`` with ``x`` an Ornstein-Uhlenbeck process (stationary std
    ``brightness_drift_std``, time constant ``brightness_drift_tau_s``), advanced to each
    frame's capture time. Noise std per pixel: ``sqrt(read^2 + gain_e * I)`` at the
    post-gain intensity ``I`` (grey levels), from a bank of standard-normal images cropped at
    random offsets (cheap; frames are not independent beyond ~3 x 64^2 combinations).
    """

    def __init__(self, cfg: CameraModelConfig, width_px: int, height_px: int, seed: int) -> None:
        self.cfg = cfg
        self.w, self.h = width_px, height_px
        self._drift_rng, self._noise_rng = rngs(seed, 2, salt=2)
        self._x = 0.0
        self._t_s: float | None = None
        self.gain = 1.0
        self.noisy = cfg.read_noise_std_dn > 0 or cfg.shot_noise_dn_per_e > 0
        self._bank: list[np.ndarray] = []
        if self.noisy:
            for _ in range(_NOISE_BANK):
                z = self._noise_rng.standard_normal((height_px + _NOISE_PAD,
                                                     width_px + _NOISE_PAD), np.float32)
                self._bank.append(z)
        self._levels = np.arange(256, dtype=np.float64)

    @property
    def active(self) -> bool:
        return self.noisy or self.cfg.brightness_drift_std > 0

    def advance(self, t_s: float) -> float:
        """Move the brightness drift to ``t_s`` (s); returns the gain."""
        c = self.cfg
        if c.brightness_drift_std <= 0:
            return 1.0
        if self._t_s is None:
            self._x = float(self._drift_rng.normal(0.0, c.brightness_drift_std))
        else:
            a = math.exp(-max(0.0, t_s - self._t_s) / c.brightness_drift_tau_s)
            self._x = a * self._x + c.brightness_drift_std * math.sqrt(1 - a * a) * float(
                self._drift_rng.normal())
        self._t_s = t_s
        self.gain = math.exp(self._x)
        return self.gain

    def sigma_dn(self, level_dn: np.ndarray | float) -> np.ndarray | float:
        """Noise std (grey levels) at post-gain intensity ``level_dn``."""
        c = self.cfg
        return np.sqrt(c.read_noise_std_dn**2 + c.shot_noise_dn_per_e * np.asarray(level_dn))

    def apply(self, image: np.ndarray, t_s: float) -> np.ndarray:
        """The mono8 frame the sensor delivers for the scene radiance ``image`` (uint8) at
        ``t_s``."""
        if not self.active:
            return image
        gain = self.advance(t_s)
        lit = np.minimum(self._levels * gain, 255.0)  # the sensor saturates
        if not self.noisy:
            return cv2.LUT(image, np.rint(lit).astype(np.uint8))
        mean = cv2.LUT(image, lit.astype(np.float32).reshape(1, 256))
        sigma = cv2.LUT(image, np.asarray(self.sigma_dn(lit), np.float32).reshape(1, 256))
        z = self._bank[int(self._noise_rng.integers(len(self._bank)))]
        dy, dx = (int(v) for v in self._noise_rng.integers(0, _NOISE_PAD, size=2))
        # rounded to nearest and saturated to 0..255 by OpenCV's conversion
        out: np.ndarray = cv2.add(mean, cv2.multiply(z[dy:dy + self.h, dx:dx + self.w], sigma),
                                  dtype=cv2.CV_8U)
        return out
