"""Contact detection in TouchRoller images: difference to a no-contact reference, pixel centres.

Two methods:

* ``"colour"`` (default). The frame is compared with a no-contact reference (mean of the first
  frames of a stream). The per-pixel score is the colour distance to the reference; the threshold
  is ``threshold_sigma`` times the noise measured on the reference frames. Candidates are found
  on a downscaled difference (cheap), and each is refined at full resolution in its own window.
  A GelSight-style membrane lights one side of an indentation and shades the other, per colour
  channel from a different direction, and not by the same amount: the brightness change is not
  centred on the contact. The centre is therefore taken, per channel, as the midpoint of the
  centroid of the brightening lobe and the centroid of the darkening lobe. Each lobe centroid
  does not depend on the lobe's amplitude, so unequal lit/shaded gains cancel; channels are
  weighted by their weaker lobe's mass. Channels without two lobes fall back to the
  magnitude-weighted centroid.
* ``"paper"``: the paper's pipeline (Sec. IV-B): grey, Gaussian blur, fixed binarisation,
  ``findContours``, centroid from ``moments``. The reference's grey image (if any) is
  subtracted first, so the fixed threshold sees the brightness change; the centroid is that of
  the brightened region, i.e. biased towards the lit side.

No ROS here: the perception node and ``touchroller contacts`` share this module.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

METHODS = ("colour", "paper")


@dataclasses.dataclass(frozen=True)
class DetectorConfig:
    """Tuning of the detector; the ROS parameters `contacts.*` map onto these fields."""

    method: str = "colour"
    threshold_sigma: float = 6.0      # threshold = this x measured noise of the colour distance
    min_threshold: float = 2.0        # grey levels; floor when the reference is noise-free
    downscale: int = 4                # candidate search on a 1/downscale image
    blur_sigma: float = 1.0           # px of the downscaled image (candidate search)
    refine_blur_sigma: float = 1.5    # px at full resolution (centre refinement)
    refine_max_pixels: int = 20000    # larger candidate windows are centred on the downscaled image
    compensate_illumination: bool = True   # per-channel gain/offset of frame vs reference (drift)
    close_size: int = 3               # morphological closing (downscaled px): merges lit and shaded lobes
    min_area: float = 64.0            # px^2 at full resolution (pixels above threshold); smaller is noise
    max_contacts: int = 32
    paper_threshold: float = 8.0      # grey levels, the paper's fixed binarisation
    paper_blur: int = 5               # Gaussian kernel size of the paper's pipeline (odd)
    paper_min_area: float = 10.0      # px^2, smallest contour the paper's pipeline keeps

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"contacts.method must be one of {METHODS}, got {self.method!r}")
        if not (self.threshold_sigma > 0 and math.isfinite(self.threshold_sigma)):
            raise ValueError(f"contacts.threshold_sigma must be positive, got {self.threshold_sigma}")
        if not (self.min_threshold >= 0 and math.isfinite(self.min_threshold)):
            raise ValueError(f"contacts.min_threshold must be >= 0, got {self.min_threshold}")
        if int(self.downscale) != self.downscale or not 1 <= self.downscale <= 16:
            raise ValueError(f"contacts.downscale must be an integer in 1..16, got {self.downscale}")
        for name in ("blur_sigma", "refine_blur_sigma"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"contacts.{name} must be >= 0, got {value}")
        if self.close_size < 0 or self.min_area < 0 or self.max_contacts < 1:
            raise ValueError("contacts.close_size and min_area must be >= 0, max_contacts >= 1")
        if self.paper_blur < 1 or self.paper_blur % 2 == 0:
            raise ValueError(f"contacts.paper_blur must be an odd kernel size, got {self.paper_blur}")

    def replace(self, **changes) -> DetectorConfig:
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class Contact:
    """One detected contact: pixel centre (u along the axis, v around it), area, confidence."""

    u: float
    v: float
    area: float          # px^2 at full resolution
    confidence: float    # 0..1: signal over threshold, halved when the blob touches the border
    peak_snr: float      # peak colour distance / noise std


FloatImage = NDArray[np.float32]


def _as_float(image: np.ndarray) -> FloatImage:
    """HxW or HxWxC image -> HxWxC float32; rejects empty, non-finite or oddly shaped input."""
    array = np.asarray(image)
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[0] < 2 or array.shape[1] < 2 or array.shape[2] not in (1, 3, 4):
        raise ValueError(f"expected an HxW or HxWx3 image, got shape {np.shape(image)}")
    if array.shape[2] == 4:
        array = array[:, :, :3]
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise ValueError("image contains non-finite values")
    if array.dtype.kind not in "uif":
        raise ValueError(f"unsupported image dtype {array.dtype}")
    return array.astype(np.float32, copy=False)


def _blur_noise_factor(sigma: float) -> float:
    """Std of white noise after a 2-D Gaussian blur of `sigma` (OpenCV's kernel), relative to before."""
    if sigma <= 0:
        return 1.0
    kernel = cv2.getGaussianKernel(_ksize(sigma), sigma).ravel()
    return float(np.sum(kernel**2))   # separable: variance x (sum k^2) per axis, two axes


def _ksize(sigma: float) -> int:
    # truncated at 2 sigma: 95% of the weight, and the kernel the noise factor is computed from
    return max(3, 2 * int(math.ceil(2.0 * sigma)) + 1)


def _blur(image: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return image
    k = _ksize(sigma)
    return cv2.GaussianBlur(image, (k, k), sigma, borderType=cv2.BORDER_REPLICATE)


def _downscale(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image
    h, w = image.shape[:2]
    # bilinear at an integer factor averages 2x2 pixels: 7x cheaper than INTER_AREA, enough to find candidates
    return cv2.resize(image, (max(1, w // factor), max(1, h // factor)), interpolation=cv2.INTER_LINEAR)


class NoContactReference:
    """Mean of no-contact frames and the noise level measured on them (per channel, in grey levels)."""

    def __init__(self, frames: Sequence[np.ndarray]):
        if len(frames) == 0:
            raise ValueError("the no-contact reference needs at least one frame")
        stack = [_as_float(f) for f in frames]
        shape = stack[0].shape
        if any(f.shape != shape for f in stack):
            raise ValueError("reference frames differ in size or channel count")
        self.shape: tuple[int, int, int] = shape
        self.mean: FloatImage = np.mean(stack, axis=0, dtype=np.float64).astype(np.float32)
        self.noise_std = _noise_std(stack, self.mean)
        self.frame_count = len(stack)
        self._frames = stack
        self._small_cache: dict[int, tuple[FloatImage, float]] = {}
        self._grey: np.ndarray | None = None

    def small(self, factor: int) -> tuple[FloatImage, float]:
        """The reference downscaled like the frames are, and the noise std measured at that scale."""
        if factor not in self._small_cache:
            smalls = [np.atleast_3d(_downscale(f, factor)) for f in self._frames]
            mean = np.mean(smalls, axis=0, dtype=np.float64).astype(np.float32)
            self._small_cache[factor] = (mean, _noise_std(smalls, mean))
        return self._small_cache[factor]

    def grey(self) -> np.ndarray:
        if self._grey is None:
            self._grey = _grey(self.mean)
        return self._grey


def _noise_std(frames: Sequence[np.ndarray], mean: np.ndarray) -> float:
    """Per-channel noise std: temporal if there are several frames, else from neighbouring pixels."""
    if len(frames) >= 2:
        residual = np.stack(frames).astype(np.float64) - mean
        return math.sqrt(float(np.mean(residual**2)) * len(frames) / (len(frames) - 1))
    # one frame: neighbouring-pixel differences (texture makes this an upper bound)
    diff = np.diff(frames[0], axis=1).ravel()
    mad = float(np.median(np.abs(diff - np.median(diff))))
    return 1.4826 * mad / math.sqrt(2.0)


def _grey(image: np.ndarray) -> np.ndarray:
    image = np.atleast_3d(image)
    if image.shape[2] == 1:
        return image[:, :, 0].astype(np.float32)
    return cv2.cvtColor(image[:, :, :3].astype(np.float32), cv2.COLOR_BGR2GRAY)


class ContactDetector:
    """Stateful detector for a stream: collects `reference_frames` frames, then detects.

    `process(image)` returns None while the reference is being captured, else the contacts.
    `recapture()` starts a new reference from the next frames.
    """

    def __init__(self, config: DetectorConfig | None = None, reference_frames: int = 5):
        if reference_frames < 1:
            raise ValueError(f"reference_frames must be >= 1, got {reference_frames}")
        self.config = config or DetectorConfig()
        self.reference_frames = int(reference_frames)
        self.reference: NoContactReference | None = None
        self._pending: list[np.ndarray] = []
        self.illumination = IlluminationState()

    # ------------------------------------------------------------------ reference
    def recapture(self, reference_frames: int | None = None) -> None:
        if reference_frames is not None:
            if reference_frames < 1:
                raise ValueError(f"reference_frames must be >= 1, got {reference_frames}")
            self.reference_frames = int(reference_frames)
        self.reference = None
        self._pending = []
        self.illumination = IlluminationState()

    def set_reference(self, frames: Iterable[np.ndarray]) -> None:
        self.reference = NoContactReference(list(frames))
        self._pending = []
        self.illumination = IlluminationState()

    @property
    def reference_ready(self) -> bool:
        return self.reference is not None

    def process(self, image: np.ndarray) -> list[Contact] | None:
        if self.reference is None:
            _as_float(image)  # reject malformed frames before they enter the reference
            self._pending.append(np.array(image, copy=True))
            if len(self._pending) >= self.reference_frames:
                self.set_reference(self._pending)
            return None
        return self.detect(image)

    # ------------------------------------------------------------------ detection
    def threshold(self) -> float:
        """Colour-distance threshold on the blurred full-resolution difference (grey levels)."""
        ref = self._require_reference()
        noise = ref.noise_std * _blur_noise_factor(self.config.refine_blur_sigma)
        return max(self.config.min_threshold, self.config.threshold_sigma * noise)

    def detect(self, image: np.ndarray) -> list[Contact]:
        if self.config.method == "paper":
            return detect_paper(image, self.reference, self.config)
        ref = self._require_reference()
        frame = np.asarray(image)
        if frame.ndim == 3 and frame.shape[2] == 4:
            frame = np.ascontiguousarray(frame[:, :, :3])   # bgra: the reference dropped alpha too
        if np.atleast_3d(frame).shape != ref.shape:
            raise ValueError(f"image shape {frame.shape} does not match the reference {ref.shape}; recapture")
        return _detect_colour(frame, ref, self.config, self.illumination)

    def _require_reference(self) -> NoContactReference:
        if self.reference is None:
            raise RuntimeError("no no-contact reference yet: feed frames with process() or call set_reference()")
        return self.reference


def _squared_norm(image: np.ndarray) -> np.ndarray:
    """Per-pixel squared colour distance of an HxWxC difference.

    Plain elementwise numpy on purpose: BLAS (einsum/matmul) is either slow for this layout or
    multi-threaded, and OpenBLAS threads collapse on a loaded machine.
    """
    out = image[:, :, 0] * image[:, :, 0]
    for c in range(1, image.shape[2]):
        out += image[:, :, c] * image[:, :, c]
    return out


@dataclasses.dataclass
class IlluminationState:
    """The last illumination fit (gain, offset per channel) and how many frames ago it was made.

    Drift is slow, so the fit (~0.5 ms) is refreshed every `refit_every` frames, and at once when
    a large part of the image exceeds the threshold (a sudden exposure change).
    """

    gain: np.ndarray | None = None
    offset: np.ndarray | None = None
    expected_small: np.ndarray | None = None   # the downscaled reference under that gain and offset
    age: int = 0
    refit_every: int = 8
    flood_fraction: float = 0.2

    def due(self) -> bool:
        return self.gain is None or self.age >= self.refit_every

    def fit(self, frame: np.ndarray, reference: np.ndarray, noise: float, threshold: float) -> None:
        self.gain, self.offset = _illumination(frame, reference, noise, threshold)
        self.expected_small = _affine(reference, self.gain, self.offset)
        self.age = 0


def _affine(image: np.ndarray, gain: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """image * gain + offset per channel. OpenCV's per-channel scalars: numpy broadcasting over a
    last axis of 3 runs ~4x slower."""
    pad = (0.0,) * (4 - image.shape[2])
    scaled = cv2.multiply(image, tuple(float(g) for g in gain) + pad)
    return np.atleast_3d(cv2.add(scaled, tuple(float(o) for o in offset) + pad))


def _detect_colour(frame: np.ndarray, ref: NoContactReference, cfg: DetectorConfig,
                   illumination: IlluminationState | None = None) -> list[Contact]:
    s = int(cfg.downscale)
    full = np.atleast_3d(frame)
    if full.dtype.kind == "f" and not np.isfinite(full).all():
        raise ValueError("image contains non-finite values")
    # 1) candidates on the downscaled colour distance
    ref_small, ref_small_noise = ref.small(s)
    small_frame = np.atleast_3d(_downscale(full, s)).astype(np.float32)
    small_noise = ref_small_noise * _blur_noise_factor(cfg.blur_sigma)
    small_threshold = max(cfg.min_threshold, cfg.threshold_sigma * small_noise)
    state: IlluminationState | None = None
    expected_small = ref_small
    if cfg.compensate_illumination:
        state = illumination if illumination is not None else IlluminationState()
        unblurred_threshold = max(cfg.min_threshold, cfg.threshold_sigma * ref_small_noise)
        fitted_now = state.due()
        if fitted_now:
            state.fit(small_frame, ref_small, ref_small_noise, unblurred_threshold)
        state.age += 1
        expected_small = state.expected_small
    small = _blur(small_frame - expected_small, cfg.blur_sigma)
    above = _squared_norm(np.atleast_3d(small)) > small_threshold**2
    if state is not None and not fitted_now and above.mean() > state.flood_fraction:
        # much of the image changed at once: an exposure step rather than contacts; refit now
        state.fit(small_frame, ref_small, ref_small_noise, unblurred_threshold)
        state.age = 1
        small = _blur(small_frame - state.expected_small, cfg.blur_sigma)
        above = _squared_norm(np.atleast_3d(small)) > small_threshold**2
    small = np.atleast_3d(small)
    if not above.any():
        return []
    mask = above.astype(np.uint8)
    if cfg.close_size > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (cfg.close_size, cfg.close_size))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    # contours are ~10x cheaper than connectedComponentsWithStats on this small mask
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    candidates = []
    for contour in contours:
        x0, y0, w, h = cv2.boundingRect(contour)
        region = np.zeros((h, w), np.uint8)
        cv2.drawContours(region, [contour], -1, 1, thickness=-1, offset=(-x0, -y0))
        # area counts only pixels above threshold: closing must not turn scattered noise into a blob
        signal_area = int(np.count_nonzero(above[y0:y0 + h, x0:x0 + w] & region.astype(bool)))
        if signal_area * s * s >= cfg.min_area:
            candidates.append((signal_area, x0, y0, w, h, region))
    candidates.sort(key=lambda c: -c[0])
    # 2) refine each candidate at full resolution in its window
    full_sigma = cfg.refine_blur_sigma
    full_noise = ref.noise_std * _blur_noise_factor(full_sigma)
    full_threshold = max(cfg.min_threshold, cfg.threshold_sigma * full_noise)
    height, width = full.shape[:2]
    contacts: list[Contact] = []
    for _, x0, y0, w, h, region in candidates:
        margin = 2 * s
        u0, v0 = max(0, x0 * s - margin), max(0, y0 * s - margin)
        u1, v1 = min(width, (x0 + w) * s + margin), min(height, (y0 + h) * s + margin)
        touches = u0 == 0 or v0 == 0 or u1 == width or v1 == height
        if (u1 - u0) * (v1 - v0) > cfg.refine_max_pixels:
            # a large blob (a contact band, a big object): its centre is already well defined on the
            # downscaled difference, and refining tens of thousands of pixels would cost milliseconds
            found = _refine(small[y0:y0 + h, x0:x0 + w], region.astype(bool), small_threshold, small_noise)
            if found is None:
                continue
            cu, cv_, npix, peak = found
            centre_shift = (s - 1) / 2.0     # centre of small pixel i is full pixel i * s + (s - 1) / 2
            confidence = max(0.0, 1.0 - small_threshold / peak) * (0.5 if touches else 1.0)
            contacts.append(Contact(u=(cu + x0) * s + centre_shift, v=(cv_ + y0) * s + centre_shift, area=float(npix * s * s),
                                    confidence=float(confidence), peak_snr=float(peak / max(small_noise, 1e-12))))
            if len(contacts) >= cfg.max_contacts:
                break
            continue
        region_full = np.zeros((v1 - v0, u1 - u0), np.uint8)
        up = cv2.resize(region, (w * s, h * s), interpolation=cv2.INTER_NEAREST)
        ry, rx = y0 * s - v0, x0 * s - u0
        region_full[ry:ry + h * s, rx:rx + w * s] = up[: v1 - v0 - ry, : u1 - u0 - rx]
        region_full = cv2.dilate(region_full, np.ones((s + 1, s + 1), np.uint8))
        expected = ref.mean[v0:v1, u0:u1]
        if state is not None:
            expected = _affine(expected, state.gain, state.offset)
        diff = full[v0:v1, u0:u1].astype(np.float32) - expected
        diff = np.atleast_3d(_blur(diff, full_sigma))
        found = _refine(diff, region_full.astype(bool), full_threshold, full_noise)
        if found is None:
            continue
        cu, cv_, npix, peak = found
        confidence = max(0.0, 1.0 - full_threshold / peak) * (0.5 if touches else 1.0)
        contacts.append(Contact(u=cu + u0, v=cv_ + v0, area=float(npix), confidence=float(confidence),
                                peak_snr=float(peak / max(full_noise, 1e-12))))
        if len(contacts) >= cfg.max_contacts:
            break
    return contacts


def _illumination(frame: np.ndarray, reference: np.ndarray, noise: float,
                  threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel gain and offset taking the reference to the frame, fitted on the background.

    LED drift or auto exposure changes the whole image by a few grey levels, which a threshold of
    a few noise std would report as one image-wide contact. The fit must not see the contacts: a
    median offset (subsampled) gives a first difference, whatever exceeds the threshold there is
    masked with a wide margin (a dent's faint tails correlate with the background's shading), and
    gain and offset are fitted by least squares on the remaining pixels.
    """
    frame, reference = frame[::2, ::2], reference[::2, ::2]     # a quarter of the pixels is plenty
    channels = frame.shape[2]
    gain = np.ones(channels, np.float32)
    shift = np.array([np.median(frame[::3, ::3, c] - reference[::3, ::3, c]) for c in range(channels)],
                     dtype=np.float32)
    contact = (_squared_norm(frame - reference - shift) > threshold**2).astype(np.uint8)
    background = cv2.dilate(contact, np.ones((5, 5), np.uint8)) == 0
    background &= (np.abs(frame - reference - shift) < 4.0 * noise + 2.0).all(axis=2)
    count = int(background.sum())
    if count < max(16, background.size // 4):     # mostly "contact": keep the robust offset only
        return gain, shift
    offset = np.zeros(channels, np.float32)
    for c in range(channels):
        fi = frame[:, :, c][background].astype(np.float64)
        ri = reference[:, :, c][background].astype(np.float64)
        r_mean, f_mean = ri.sum() / count, fi.sum() / count
        r_centred = ri - r_mean
        variance = float((r_centred * r_centred).sum())
        g = float((r_centred * (fi - f_mean)).sum()) / variance if variance > 1e-6 * count else 1.0
        gain[c] = min(max(g, 0.5), 2.0)      # beyond this it is not drift: let the detector see it
        offset[c] = f_mean - gain[c] * r_mean
    return gain, offset


def _refine(diff: np.ndarray, region: np.ndarray, threshold: float, noise: float):
    """Colour-aware centre of one blob in its window: (u, v, area px, peak distance) or None."""
    score = np.sqrt(_squared_norm(diff))
    inside = region & (score > threshold)
    npix = int(inside.sum())
    if npix == 0:
        return None
    ys, xs = np.nonzero(inside)
    values = diff[ys, xs]                                       # (n, C) signed changes
    channels = values.shape[1]
    lobes = np.empty((values.shape[0], 2 * channels), np.float64)   # brightening | darkening
    np.maximum(values, 0.0, out=lobes[:, :channels])
    np.maximum(-values, 0.0, out=lobes[:, channels:])
    mass = lobes.sum(axis=0)                                    # (2C,)
    x = xs.astype(np.float64)[:, None]
    y = ys.astype(np.float64)[:, None]
    moments = np.stack([(lobes * x).sum(axis=0), (lobes * y).sum(axis=0)])   # (2, 2C), no BLAS
    mass_pos, mass_neg = mass[:channels], mass[channels:]
    weight = np.minimum(mass_pos, mass_neg)
    # a channel counts when both lobes carry real signal, not just noise leaking through the mask
    bipolar = (weight > 0.1 * np.maximum(mass_pos, mass_neg)) & (weight > 3.0 * noise * math.sqrt(npix))
    peak = float(score[ys, xs].max())
    if bipolar.any():
        w = weight[bipolar]
        centre_pos = moments[:, :channels][:, bipolar] / mass_pos[bipolar]      # (2, k) lobe centroids
        centre_neg = moments[:, channels:][:, bipolar] / mass_neg[bipolar]
        u, v = (0.5 * (centre_pos + centre_neg) * w).sum(axis=1) / w.sum()
        return float(u), float(v), npix, peak
    magnitude = score[ys, xs].astype(np.float64)
    total = magnitude.sum()
    return float((magnitude * x[:, 0]).sum() / total), float((magnitude * y[:, 0]).sum() / total), npix, peak


def detect_paper(image: np.ndarray, reference: NoContactReference | None,
                 config: DetectorConfig | None = None) -> list[Contact]:
    """The paper's pipeline: grey, Gaussian blur, fixed binarisation, findContours, moments centroid."""
    cfg = config or DetectorConfig(method="paper")
    frame = _as_float(image)
    grey = _grey(frame)
    if reference is not None:
        if reference.shape[:2] != frame.shape[:2]:
            raise ValueError(f"image shape {np.shape(image)} does not match the reference {reference.shape}")
        grey = grey - reference.grey()
    k = int(cfg.paper_blur)
    grey = cv2.GaussianBlur(grey, (k, k), 0)
    binary = (grey > cfg.paper_threshold).astype(np.uint8)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    contacts = []
    for contour in contours:
        m = cv2.moments(contour)
        if m["m00"] <= 0 or m["m00"] < cfg.paper_min_area:
            continue
        contacts.append(Contact(u=m["m10"] / m["m00"], v=m["m01"] / m["m00"], area=float(m["m00"]),
                                confidence=1.0, peak_snr=float("nan")))
    contacts.sort(key=lambda c: -c.area)
    return contacts[: cfg.max_contacts]
