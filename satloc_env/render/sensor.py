"""What a real camera adds to the rendered image: vignetting, motion blur and sensor noise.

:class:`Sensor` of ``strength`` 1 is an automotive colour camera in daylight, the kind KITTI and Malaga drove
with (an exposure of at most 2 ms, the limit KITTI's rig set its shutters to, a lens that darkens its corners, photon and read noise of a few grey
levels); 0 is the identity (the renderer's exact pixels). Per frame:

* **motion blur** over the exposure ``exposure_s``: a horizontal smear of ``|yaw rate| x exposure x fx``
  pixels from the car's turning, and a zoom about the principal point from its forward motion, of the size a
  point at ``blur_depth_m`` moves (``speed x exposure / blur_depth_m`` of its distance from the centre);
* **vignetting**: the image darkened by ``vignetting x (r / r_corner)^2`` towards its corners;
* **noise**: Poisson-Gaussian, a standard deviation of ``sqrt(shot x I + read^2)`` grey levels at intensity
  ``I``, drawn from the episode's seed (a few precomputed fields of normal noise, each frame a random window of
  one: independent enough between frames, and cheap).

All of it scales with ``strength``. Each frame's draws come from the generator the sensor was made with, so an
episode with a seed renders the same noise every time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["SensorParams", "Sensor"]


@dataclass(frozen=True)
class SensorParams:
    """A camera at ``strength`` 1 (see the module docstring): exposure (s), the depth whose forward motion sets
    the zoom blur (m), the corners' darkening, the shot-noise gain and the read noise (grey levels)."""

    exposure_s: float = 0.002
    blur_depth_m: float = 8.0
    vignetting: float = 0.3
    shot: float = 0.04
    read: float = 1.5


_FIELDS, _MARGIN = 2, 32


class Sensor:
    """Vignetting, motion blur and noise of strength ``strength`` (0 to 1) for ``width`` x ``height`` images with
    focal length ``fx`` and principal point (``cx``, ``cy``) pixels; draws from ``rng``."""

    def __init__(self, strength: float, width: int, height: int, fx: float, cx: float, cy: float,
                 rng: np.random.Generator, params: SensorParams = SensorParams()):
        if not (math.isfinite(strength) and 0.0 <= strength <= 1.0):
            raise ValueError(f"sensor strength: expected a number in [0, 1], got {strength}")
        self.strength, self.p = float(strength), params
        self.size, self.fx, self.c = (int(width), int(height)), float(fx), (float(cx), float(cy))
        self.rng = rng
        if self.strength == 0.0:
            return
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        r2 = (xx - cx) ** 2 + (yy - cy) ** 2
        corner = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0, width) for y in (0, height))
        gain = (1.0 - self.strength * params.vignetting * r2 / corner).astype(np.float32)
        self.gain = cv2.merge([gain, gain, gain])
        i = np.arange(256, dtype=np.float32)
        self.sigma = (self.strength * np.sqrt(params.shot * i + params.read ** 2)).astype(np.float32).reshape(256, 1)
        shape = (_FIELDS, height + _MARGIN, width + _MARGIN, 3)
        # float16 values (as the fields were first stored) held as float32: the same noise, multiplied without
        # numpy's slow float16 arithmetic
        self.fields = rng.standard_normal(shape, dtype=np.float32).astype(np.float16).astype(np.float32)

    def __call__(self, img: np.ndarray, speed_mps: float = 0.0, yaw_rate: float = 0.0) -> np.ndarray:
        """``img`` (H x W x 3 uint8) as the camera records it while the car moves at ``speed_mps`` and turns at
        ``yaw_rate`` rad/s."""
        if self.strength == 0.0:
            return img
        s, p = self.strength, self.p
        out = img
        zoom = s * abs(speed_mps) * p.exposure_s / p.blur_depth_m
        if zoom * max(self.size) / 2 > 1.0:                  # forward motion (a pixel or more): three zooms
            acc = out.astype(np.float32)
            for k in (0.5, 1.0):
                m = cv2.getRotationMatrix2D(self.c, 0.0, 1.0 + zoom * k)
                acc += cv2.warpAffine(out, m, self.size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
            out = acc / 3.0
        smear = s * abs(yaw_rate) * p.exposure_s * self.fx
        if smear > 1.0:                                       # turning (a pixel or more): a horizontal smear
            n = int(math.ceil(smear)) | 1
            kernel = np.zeros((1, n), np.float32)
            kernel[0] = 1.0 / n
            out = cv2.filter2D(out.astype(np.float32), -1, kernel, borderType=cv2.BORDER_REFLECT)
        out = np.clip(out + 0.5, 0, 255).astype(np.uint8) if out.dtype != np.uint8 else out
        k = int(self.rng.integers(_FIELDS))
        dy, dx = (int(v) for v in self.rng.integers(0, _MARGIN, 2))
        h, w = img.shape[:2]
        f = cv2.multiply(out, self.gain, dtype=cv2.CV_32F)                        # vignetting
        noise = cv2.LUT(out, self.sigma)                                          # noise at the intensity
        cv2.multiply(noise, self.fields[k, dy:dy + h, dx:dx + w], dst=noise)
        return cv2.add(f, noise, dtype=cv2.CV_8U)                                 # rounded, saturated
