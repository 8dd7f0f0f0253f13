"""Optional image effects. Each is a plain function; the renderer calls only those a scene lists.

Static effects (gel background, vignetting) are computed once into a gain/offset pair; per-frame
effects (blur, noise, compression, drops) are called per frame. Tests count calls to these functions
to show that an effect left out costs nothing.
"""
from __future__ import annotations

import math

import cv2
import numpy as np


# --------------------------------------------------------------------------- static (once per sensor)
def gel_background(height: int, width: int, rng: np.random.Generator, *, illumination: float = 0.12,
                   led_falloff: float = 0.25, specks: int = 60,
                   speck_radius_px: tuple[float, float] = (1.0, 3.0)) -> tuple[np.ndarray, np.ndarray]:
    """Uneven LED illumination and specks fixed to the camera: (gain HxWx3, offset HxWx3) float32.

    Illumination: a smooth random field (amplitude `illumination`) times a fall-off away from the LEDs,
    which sit beside the camera (brighter at the image's top and bottom edges, per colour).
    Specks: dust and bubbles in the gel/glass, dark (absorbing) or bright (scattering) small blobs.
    """
    small = rng.standard_normal((6, 8, 3)).astype(np.float32)
    field = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    field /= max(float(np.abs(field).max()), 1e-6)
    v = np.linspace(-1.0, 1.0, height, dtype=np.float32)[:, None, None]
    u = np.linspace(-1.0, 1.0, width, dtype=np.float32)[None, :, None]
    # Each colour's LED is on a different side: the fall-off direction rotates with the channel.
    angles = np.array([math.radians(a) for a in (200.0, 80.0, 320.0)], dtype=np.float32)
    ramp = u * np.cos(angles)[None, None, :] + v * np.sin(angles)[None, None, :]
    gain = (1.0 + illumination * field) * (1.0 + 0.5 * led_falloff * ramp)
    offset = np.zeros((height, width, 3), np.float32)
    if specks > 0:
        mask = np.zeros((height, width), np.float32)
        bright = np.zeros((height, width), np.float32)
        lo, hi = speck_radius_px
        for _ in range(int(specks)):
            centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
            radius = max(1, round(float(rng.uniform(lo, hi))))
            if rng.random() < 0.8:
                cv2.circle(mask, centre, radius, float(rng.uniform(0.3, 0.8)), -1, cv2.LINE_AA)
            else:
                cv2.circle(bright, centre, radius, float(rng.uniform(20.0, 60.0)), -1, cv2.LINE_AA)
        mask = cv2.GaussianBlur(mask, (0, 0), 0.7)
        gain *= (1.0 - np.clip(mask, 0.0, 0.95))[:, :, None]
        offset += cv2.GaussianBlur(bright, (0, 0), 0.7)[:, :, None]
    return gain.astype(np.float32), offset


def vignetting(height: int, width: int, fx: float, fy: float, cx: float, cy: float,
               strength: float = 0.35) -> np.ndarray:
    """Natural vignetting: 1 - strength * (1 - cos^4 of the pixel's off-axis angle), HxW float32."""
    u = (np.arange(width, dtype=np.float64) - cx) / fx
    v = (np.arange(height, dtype=np.float64) - cy) / fy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    cos4 = 1.0 / (1.0 + r2) ** 2
    return (1.0 - strength * (1.0 - cos4)).astype(np.float32)


# --------------------------------------------------------------------------- per frame
def motion_blur(relief: np.ndarray, length_px: float) -> np.ndarray:
    """Box blur along image rows' direction (v) of `length_px` pixels (fractional lengths allowed).

    Applied to the relief as seen by the camera (the moving part of the scene), not to the static
    contact band or the gel background, which do not move relative to the camera.
    """
    if length_px <= 1.0:
        return relief
    n = int(math.ceil(length_px))
    if n % 2 == 0:
        n += 1
    kernel = np.zeros((n, 1), np.float32)
    half = length_px / 2.0
    centre = n // 2
    for k in range(n):   # exact overlap of each tap's pixel [k-0.5, k+0.5] with [-half, half]
        lo = max(k - centre - 0.5, -half)
        hi = min(k - centre + 0.5, half)
        kernel[k, 0] = max(0.0, hi - lo)
    kernel /= kernel.sum()
    return cv2.filter2D(relief, -1, kernel, borderType=cv2.BORDER_REPLICATE)


class NoiseBank:
    """Gaussian read noise (sigma DN), drawn once and sliced at a random offset per frame.

    Drawing 0.9 M normal samples per frame would dominate the frame time; a bank of a few frames
    sliced at random offsets is statistically the same per pixel (temporal correlation only across
    frames that happen to overlap in the bank, which a random offset makes rare).
    """

    def __init__(self, shape: tuple[int, ...], sigma: float, rng: np.random.Generator, frames: int = 3,
                 shot_dn_per_electron: float = 0.0) -> None:
        self.shape = shape
        self.size = int(np.prod(shape))
        self.rng = rng
        self.sigma = float(sigma)
        self.shot = float(shot_dn_per_electron)
        self.salt = int(rng.integers(0, 2**31))
        if self.shot > 0:   # signal-dependent: keep unit normals, scale per pixel per frame
            self.unit = rng.standard_normal(self.size * frames).astype(np.float32)
            return
        noise = np.rint(rng.standard_normal(self.size * frames) * sigma)
        self.positive = np.clip(noise, 0, 255).astype(np.uint8)
        self.negative = np.clip(-noise, 0, 255).astype(np.uint8)


def _bank_offset(bank: NoiseBank, span: int, frame: int | None) -> int:
    """Where this frame's noise starts in the bank: random, or fixed by the frame's index (the same frame
    of the same scene and seed always gets the same noise, however many frames were rendered before)."""
    if frame is None:
        return int(bank.rng.integers(0, span))
    return (int(frame) * 2654435761 + bank.salt) % span   # Knuth's multiplicative hash: frames spread out


def add_noise(image: np.ndarray, bank: NoiseBank, frame: int | None = None) -> np.ndarray:
    """Saturating uint8 image + noise from the bank (in place); `frame` fixes the noise to a frame index.

    Read noise only: sigma DN. With `shot_dn_per_electron` = g > 0, photon shot noise is added:
    variance sigma^2 + g * signal (DN^2), i.e. Poisson statistics of signal / g electrons.
    """
    if bank.shot > 0:
        start = _bank_offset(bank, bank.unit.size - bank.size + 1, frame)
        unit = bank.unit[start:start + bank.size].reshape(bank.shape)
        signal = image.astype(np.float32)
        std = cv2.sqrt(signal * np.float32(bank.shot) + np.float32(bank.sigma**2))
        noisy = cv2.add(signal, cv2.multiply(unit, std))
        np.copyto(image, cv2.convertScaleAbs(np.maximum(noisy, 0.0)))
        return image
    start = _bank_offset(bank, bank.positive.size - bank.size + 1, frame)
    pos = bank.positive[start:start + bank.size].reshape(bank.shape)
    neg = bank.negative[start:start + bank.size].reshape(bank.shape)
    cv2.add(image, pos, dst=image)
    cv2.subtract(image, neg, dst=image)
    return image


def compress(image: np.ndarray, quality: int) -> np.ndarray:
    """JPEG round trip (a webcam streaming MJPEG)."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)


def frame_dropped(rng: np.random.Generator, probability: float, frame: int | None = None, seed: int = 0) -> bool:
    """Whether a frame is lost: random, or fixed by the frame's index (and the seed)."""
    if frame is None:
        return bool(rng.random() < probability)
    return bool(np.random.default_rng([int(seed), int(frame)]).random() < probability)
