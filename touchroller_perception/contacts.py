"""Contact detection in TouchRoller images: difference to a no-contact reference, pixel centres.

Two methods:

* ``"colour"`` (default). The frame is compared with a no-contact reference (mean of the first
  frames of a stream). The per-pixel score is the colour distance to the reference; the threshold
  is ``threshold_sigma`` times the noise measured on the reference frames. Candidates are found
  on a downscaled difference (cheap), and each is refined at full resolution in its own window.
  All windows of a frame are refined in one batch: they are packed into one mosaic image, each
  padded with its own edge pixels, so the result equals refining each window alone while the
  per-blob cost is a few slice copies instead of a dozen OpenCV/numpy calls. Blobs whose whole
  downscaled bounding box is smaller than ``min_area`` are dropped before they are drawn: they
  cannot reach ``min_area`` (textured frames have dozens of such specks).
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
import functools
import math
from collections.abc import Iterable, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from touchroller_perception.images import to_grey

METHODS = ("colour", "paper")
MEDIAN_SAMPLES = 1536    # pixels per channel for the background's medians (see _sample)


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
    min_area: float = 100.0           # px^2 at full resolution: a contact's area (extent); smaller is dust or noise
    max_contacts: int = 32
    background_sigma: float = 96.0    # px at full resolution: smooth shading field of the difference (0: off)
    lobe_fraction: float = 0.4        # centre from each lobe's part above this fraction of the lobe's peak
    extent_fraction: float = 0.3      # a contact's area/ellipse: colour distance above this fraction of its peak
    min_score: float = 12.0           # smallest contact peak, in noise std of the difference (see Contact.score)
    border: float = 16.0              # px at full resolution: a band along the edges not searched (lens edge, glare)
    adapt_rate: float = 0.05          # weight of a quiet frame blended into the reference (0: never adapt)
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
        if not (self.background_sigma >= 0 and math.isfinite(self.background_sigma)):
            raise ValueError(f"contacts.background_sigma must be >= 0, got {self.background_sigma}")
        for name in ("lobe_fraction", "extent_fraction", "adapt_rate"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ValueError(f"contacts.{name} must be in [0, 1), got {value}")
        if not (self.border >= 0 and math.isfinite(self.border)):
            raise ValueError(f"contacts.border must be >= 0, got {self.border}")
        if not (self.min_score >= 0 and math.isfinite(self.min_score)):
            raise ValueError(f"contacts.min_score must be >= 0, got {self.min_score}")
        if self.paper_blur < 1 or self.paper_blur % 2 == 0:
            raise ValueError(f"contacts.paper_blur must be an odd kernel size, got {self.paper_blur}")

    def replace(self, **changes) -> DetectorConfig:
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class Contact:
    """One detected contact: pixel centre (u along the axis, v around it), size, shape and strength.

    The shape is the ellipse with the second moments of the contact's pixels (those whose colour
    change exceeds `extent_fraction` of the contact's peak), as PyTouch's ContactArea reports it.
    """

    u: float
    v: float
    area: float          # px^2 at full resolution: pixels above extent_fraction of the peak
    confidence: float    # 0..1: signal over threshold, halved when the blob touches the border
    score: float         # peak colour change in noise standard deviations of the difference (detection scale)
    major_axis: float = math.nan   # full length of the ellipse's major axis, px
    minor_axis: float = math.nan   # full length of the minor axis, px
    angle: float = math.nan        # major axis from +u towards +v, radians in (-pi/2, pi/2]


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


@functools.lru_cache(maxsize=64)
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
    """Mean of no-contact frames and the noise level measured on them (per channel, in grey levels).

    The frames fix the image format (size, channels, dtype): frames of another format are refused
    rather than compared with it. `blend` moves the mean towards a new no-contact frame (the slow
    adaptive update).
    """

    def __init__(self, frames: Sequence[np.ndarray]):
        if len(frames) == 0:
            raise ValueError("the no-contact reference needs at least one frame")
        formats = {_image_format(f) for f in frames}
        if len(formats) > 1:
            raise ValueError("reference frames differ in size, channel count or dtype")
        stack = [_as_float(f) for f in frames]
        self.shape: tuple[int, int, int] = stack[0].shape
        self.dtype = np.asarray(frames[0]).dtype
        self.mean: FloatImage = np.asarray(np.mean(stack, axis=0, dtype=np.float64), np.float32)
        self.noise_std = _noise_std(stack, self.mean)
        self.frame_count = len(stack)
        self._frames = stack
        self._small_cache: dict[int, tuple[FloatImage, float]] = {}
        self._grey: np.ndarray | None = None

    def small(self, factor: int) -> tuple[FloatImage, float]:
        """The reference downscaled like the frames are, and the noise std measured at that scale."""
        if factor not in self._small_cache:
            smalls = [np.atleast_3d(_downscale(f, factor)) for f in self._frames]
            noise = _noise_std(smalls, np.asarray(np.mean(smalls, axis=0, dtype=np.float64), np.float32))
            # bilinear downscaling is linear: the downscaled mean is the mean of the downscaled frames
            self._small_cache[factor] = (np.atleast_3d(_downscale(self.mean, factor)), noise)
        return self._small_cache[factor]

    def grey(self) -> np.ndarray:
        if self._grey is None:
            self._grey = to_grey(self.mean, uint8=False)
        return self._grey

    def matches(self, image: np.ndarray) -> bool:
        """True if `image` has the reference's size, channel count and dtype (bgra counts as bgr)."""
        array = np.asarray(image)
        if array.ndim == 3 and array.shape[2] == 4:
            array = array[:, :, :3]
        return np.atleast_3d(array).shape == self.shape and array.dtype == self.dtype

    def blend(self, frame: np.ndarray, rate: float) -> None:
        """mean <- (1 - rate) mean + rate frame: follows slow drift seen while nothing touches."""
        cv2.accumulateWeighted(_as_float(frame), self.mean, rate)
        self._small_cache = {f: (np.atleast_3d(_downscale(self.mean, f)), noise)
                             for f, (_, noise) in self._small_cache.items()}
        self._grey = None


def _image_format(image: np.ndarray) -> tuple[tuple[int, ...], np.dtype]:
    array = np.asarray(image)
    channels = array.shape[2] if array.ndim == 3 else 1
    return (array.shape[:2] + (3 if channels == 4 else channels,), array.dtype)


def _noise_std(frames: Sequence[np.ndarray], mean: np.ndarray) -> float:
    """Per-channel noise std: temporal if there are several frames, else from neighbouring pixels."""
    if len(frames) >= 2:
        residual = np.stack(frames).astype(np.float64) - mean
        return math.sqrt(float(np.mean(residual**2)) * len(frames) / (len(frames) - 1))
    # one frame: neighbouring-pixel differences (texture makes this an upper bound)
    diff = np.diff(frames[0], axis=1).ravel()
    mad = float(np.median(np.abs(diff - np.median(diff))))
    return 1.4826 * mad / math.sqrt(2.0)


class ContactDetector:
    """Stateful detector for a stream: collects `reference_frames` frames, then detects.

    `process(image)` returns None while the reference is being captured, else the contacts.
    `recapture()` starts a new reference from the next frames. Frames whose format (size, channels,
    dtype) differs from the reference are refused with a ValueError; the reference stays until it
    is recaptured on request. While nothing touches, the reference follows slow drift (see
    `BackgroundModel` and `DetectorConfig.adapt_rate`).
    """

    def __init__(self, config: DetectorConfig | None = None, reference_frames: int = 5):
        if reference_frames < 1:
            raise ValueError(f"reference_frames must be >= 1, got {reference_frames}")
        self.config = config or DetectorConfig()
        self.reference_frames = int(reference_frames)
        self.reference: NoContactReference | None = None
        self._pending: list[np.ndarray] = []
        self.background = BackgroundModel()

    # ------------------------------------------------------------------ reference
    def recapture(self, reference_frames: int | None = None) -> None:
        if reference_frames is not None:
            if reference_frames < 1:
                raise ValueError(f"reference_frames must be >= 1, got {reference_frames}")
            self.reference_frames = int(reference_frames)
        self.reference = None
        self._pending = []
        self.background = BackgroundModel()

    def set_reference(self, frames: Iterable[np.ndarray]) -> None:
        self.reference = NoContactReference(list(frames))
        self._pending = []
        self.background = BackgroundModel()

    @property
    def reference_ready(self) -> bool:
        return self.reference is not None

    def process(self, image: np.ndarray) -> list[Contact] | None:
        if self.reference is None:
            _as_float(image)  # reject malformed frames before they enter the reference
            if self._pending and _image_format(image) != _image_format(self._pending[0]):
                raise ValueError(f"frame {_describe(image)} differs from the reference frames collected so far "
                                 f"({_describe(self._pending[0])}); refused")
            self._pending.append(np.array(image, copy=True))
            if len(self._pending) >= self.reference_frames:
                self.set_reference(self._pending)
            return None
        return self.detect(image)

    # ------------------------------------------------------------------ detection
    def threshold(self) -> float:
        """Colour-distance threshold on the blurred downscaled difference (grey levels), once measured."""
        self._require_reference()
        noise = self.background.noise
        return math.nan if noise is None else max(self.config.min_threshold, self.config.threshold_sigma * noise)

    def detect(self, image: np.ndarray) -> list[Contact]:
        if self.config.method == "paper":
            return detect_paper(image, self.reference, self.config)
        ref = self._require_reference()
        frame = np.asarray(image)
        if frame.ndim == 3 and frame.shape[2] == 4:
            frame = np.ascontiguousarray(frame[:, :, :3])   # bgra: the reference dropped alpha too
        if not ref.matches(frame):
            raise ValueError(f"image {_describe(image)} does not match the reference ({_describe_reference(ref)})")
        return _detect_colour(frame, ref, self.config, self.background)

    def _require_reference(self) -> NoContactReference:
        if self.reference is None:
            raise RuntimeError("no no-contact reference yet: feed frames with process() or call set_reference()")
        return self.reference


def _describe(image: np.ndarray) -> str:
    array = np.asarray(image)
    return f"{'x'.join(str(n) for n in array.shape)} {array.dtype}"


def _describe_reference(ref: NoContactReference) -> str:
    shape = ref.shape if ref.shape[2] > 1 else ref.shape[:2]
    return f"{'x'.join(str(n) for n in shape)} {ref.dtype}"


def _squared_norm(image: np.ndarray) -> np.ndarray:
    """Per-pixel squared colour distance of an HxWxC difference.

    No BLAS (einsum/matmul): it is either slow for this layout or multi-threaded, and OpenBLAS
    threads collapse on a loaded machine. For float32, OpenCV squares and sums the channels in two
    passes (the same sums, in the same order, as the elementwise numpy below, which takes five).
    """
    if image.dtype == np.float32:
        return cv2.transform(cv2.multiply(image, image), np.ones((1, image.shape[2]), np.float32))
    out = image[:, :, 0] * image[:, :, 0]
    for c in range(1, image.shape[2]):
        out += image[:, :, c] * image[:, :, c]
    return out


@dataclasses.dataclass
class BackgroundModel:
    """What a frame without contact looks like, relative to the reference, and how noisy it is.

    Fitted on the downscaled frame (every `refit_every` frames; drift is slow): a per-channel gain
    and offset (exposure, LED drift), then a smooth shading field of what is left (normalised
    Gaussian of scale `background_sigma` over the pixels that are not contacts), then the noise:
    1.4826 x the median absolute deviation of the blurred remaining difference, per channel (the
    RMS over channels is `noise`). Measured on the difference itself, the noise needs only one
    reference frame and includes what the model does not explain (texture, compression).
    A large part of the image over the threshold between fits (more than `flood_fraction`: an exposure
    step) refits at once. When such a refit leaves as much of the image changed (a roll over a textured
    surface keeps a fifth of it changed: no gain, offset or smooth field explains that), that share is
    `unexplained_fraction`, and only `flood_fraction` more than it refits again before the next
    scheduled fit, instead of a useless refit on every frame.
    """

    gain: np.ndarray | None = None
    offset: np.ndarray | None = None
    field_small: np.ndarray | None = None      # smooth shading at the detection scale (None: off)
    expected_small: np.ndarray | None = None   # the downscaled reference under gain, offset and field
    noise: float | None = None                 # noise std of the blurred downscaled difference (per channel, RMS)
    age: int = 0
    refit_every: int = 8
    flood_fraction: float = 0.2
    quiet_frames: int = 0                      # frames in a row without any candidate blob
    unexplained_fraction: float = 0.0          # share over the threshold that the last flood refit left
    _expected_full: np.ndarray | None = None

    def due(self) -> bool:
        return self.gain is None or self.age >= self.refit_every

    def fit(self, small_frame: np.ndarray, ref_small: np.ndarray, cfg: DetectorConfig, scale: int) -> None:
        frame = small_frame.astype(np.float32, copy=False)
        channels = frame.shape[2]
        raw = np.atleast_3d(cv2.subtract(frame, ref_small))
        sample = _sample(raw)
        shift = _channel_medians(sample)
        raw_noise = _mad_noise(np.atleast_3d(cv2.subtract(sample, _scalar(shift))))
        raw_threshold = max(cfg.min_threshold, cfg.threshold_sigma * raw_noise)
        if cfg.compensate_illumination:
            self.gain, self.offset = _illumination(frame, ref_small, raw_noise, raw_threshold)
        else:
            self.gain, self.offset = np.ones(channels, np.float32), np.zeros(channels, np.float32)
        expected = _affine(ref_small, self.gain, self.offset)
        self.field_small = None
        if cfg.compensate_illumination and cfg.background_sigma > 0:
            self.field_small = _smooth_field(np.atleast_3d(cv2.subtract(frame, expected)), raw_threshold,
                                             cfg.background_sigma / scale)
            expected = np.atleast_3d(cv2.add(expected, self.field_small))
        self.expected_small = expected
        residual = np.atleast_3d(_blur(np.atleast_3d(cv2.subtract(frame, expected)), cfg.blur_sigma))
        self.noise = _mad_noise(_sample(residual))
        self._expected_full = None
        self.age = 0

    def expected_full(self, reference: NoContactReference) -> np.ndarray:
        """The full-resolution reference under the fitted gain, offset and field (made when first needed)."""
        if self._expected_full is None:
            assert self.gain is not None and self.offset is not None
            expected = _affine(reference.mean, self.gain, self.offset)
            if self.field_small is not None:
                height, width = reference.shape[:2]
                field = np.atleast_3d(cv2.resize(self.field_small, (width, height), interpolation=cv2.INTER_LINEAR))
                expected = np.atleast_3d(cv2.add(expected, field))
            self._expected_full = expected
        return self._expected_full


def _sample(image: np.ndarray, count: int = MEDIAN_SAMPLES) -> np.ndarray:
    """Every k-th pixel of every k-th row (k >= 2: neighbours of the blurred difference are correlated),
    k chosen to keep about `count` pixels (at least as many).

    Medians and MADs of the background need only a sample: over ~1500 pixels the MAD's own relative
    spread is ~4%, and a partition of 1500 values costs a quarter of one of 6000.
    """
    height, width = image.shape[:2]
    step = max(2, int(math.sqrt(height * width / count)))
    return image[::step, ::step]


def _mad_noise(residual: np.ndarray) -> float:
    """RMS over channels of the per-channel robust std (1.4826 x median absolute deviation)."""
    centre = _channel_medians(residual)
    spread = _channel_medians(np.abs(np.atleast_3d(cv2.subtract(residual, _scalar(centre)))))
    return float(1.4826 * math.sqrt(float(np.mean(np.square(spread, dtype=np.float64)))))


def _smooth_field(residual: np.ndarray, threshold: float, sigma: float) -> np.ndarray:
    """A smooth per-channel field through the residual where it is not a contact (normalised convolution).

    Computed on a 4x coarser grid (the field is smooth at the scale `sigma`, in pixels of
    `residual`), then resized back. Pixels over the threshold, grown by a margin, do not count:
    a contact must not become part of its own background.
    """
    height, width, channels = residual.shape
    contact = (_squared_norm(residual) > threshold * threshold).astype(np.uint8)
    keep = (cv2.dilate(contact, np.ones((5, 5), np.uint8)) == 0).astype(np.float32)
    q = 4 if min(height, width) >= 32 else 1
    size = (max(1, width // q), max(1, height // q))
    weight = cv2.resize(keep, size, interpolation=cv2.INTER_AREA)
    values = np.atleast_3d(cv2.resize(residual * keep[:, :, None], size, interpolation=cv2.INTER_AREA))
    coarse_sigma = max(sigma / q, 0.5)
    weight = cv2.GaussianBlur(weight, (0, 0), coarse_sigma, borderType=cv2.BORDER_REFLECT)
    values = np.atleast_3d(cv2.GaussianBlur(values, (0, 0), coarse_sigma, borderType=cv2.BORDER_REFLECT))
    field = values / np.maximum(weight, 1e-3)[:, :, None]
    field[weight < 1e-3] = 0.0
    return np.atleast_3d(cv2.resize(field, (width, height), interpolation=cv2.INTER_LINEAR)).astype(np.float32)


def _difference(frame: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """frame (any dtype) as float32 minus expected (float32); one pass for bgr8 instead of two."""
    if frame.dtype == np.uint8 and frame.shape == expected.shape:
        return np.atleast_3d(cv2.subtract(frame, expected, dtype=cv2.CV_32F))
    return frame.astype(np.float32) - expected


def _scalar(values: np.ndarray) -> tuple[float, float, float, float]:
    """Per-channel values as an OpenCV scalar (numpy broadcasting over a last axis of 3 runs ~4x slower)."""
    padded = [float(v) for v in values] + [0.0] * (4 - len(values))
    return padded[0], padded[1], padded[2], padded[3]


def _affine(image: np.ndarray, gain: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """image * gain + offset per channel, with OpenCV's per-channel scalars."""
    return np.atleast_3d(cv2.add(cv2.multiply(image, _scalar(gain)), _scalar(offset)))


def _detect_colour(frame: np.ndarray, ref: NoContactReference, cfg: DetectorConfig,
                   background: BackgroundModel | None = None) -> list[Contact]:
    s = int(cfg.downscale)
    full = np.atleast_3d(frame)
    if full.dtype.kind == "f" and not np.isfinite(full).all():
        raise ValueError("image contains non-finite values")
    state = background if background is not None else BackgroundModel()
    small_frame = np.atleast_3d(_downscale(full, s)).astype(np.float32, copy=False)
    # 1) the background model: refitted every few frames; the reference follows slow drift while quiet
    fitted_now = state.due()
    if fitted_now:
        if cfg.adapt_rate > 0 and state.gain is not None and state.quiet_frames >= state.refit_every:
            ref.blend(full, cfg.adapt_rate)
        state.fit(small_frame, ref.small(s)[0], cfg, s)
    state.age += 1
    small, small_sq, above, small_threshold = _small_difference(small_frame, state, cfg)
    changed = np.count_nonzero(above) / above.size
    if fitted_now and changed <= state.flood_fraction:
        state.unexplained_fraction = 0.0
    elif not fitted_now and changed > state.unexplained_fraction + state.flood_fraction:
        # much of the image changed at once: an exposure step rather than contacts; refit now
        state.fit(small_frame, ref.small(s)[0], cfg, s)
        state.age = 1
        small, small_sq, above, small_threshold = _small_difference(small_frame, state, cfg)
        left = np.count_nonzero(above) / above.size
        state.unexplained_fraction = left if left > state.flood_fraction else 0.0
    # 2) candidates: blobs of the closed mask, large enough and significant enough
    candidates = _candidates_of(above, small_sq, s, cfg) if above.any() else []
    state.quiet_frames = state.quiet_frames + 1 if not candidates else 0
    small_noise = max(float(state.noise or 0.0), 1e-12)
    strong = [c for c in candidates if math.sqrt(c[6]) >= cfg.min_score * small_noise]
    if not strong:
        return []
    # 3) refine each candidate: at full resolution in its window (all windows in one batch), or on
    # the downscaled difference when the window is large
    full_sigma = cfg.refine_blur_sigma
    full_noise = small_noise * _full_to_small_noise(ref, s, cfg)
    full_threshold = max(cfg.min_threshold, cfg.threshold_sigma * full_noise)
    height, width = full.shape[:2]
    margin = 2 * s
    contacts: list[Contact] = []
    pending = strong
    while pending and len(contacts) < cfg.max_contacts:
        # refine only as many candidates as could still become contacts (a flood of blobs stays cheap)
        room = min(cfg.max_contacts - len(contacts), 65534)    # window labels are uint16 at most
        chunk, pending = pending[:room], pending[room:]
        windows = []
        for _, x0, y0, w, h, _region, _peak in chunk:
            u0, v0 = max(0, x0 * s - margin), max(0, y0 * s - margin)
            u1, v1 = min(width, (x0 + w) * s + margin), min(height, (y0 + h) * s + margin)
            windows.append((u0, v0, u1, v1))
        # a large blob (a contact band, a big object): its centre is already well defined on the
        # downscaled difference, and refining tens of thousands of pixels would cost milliseconds
        large = [(u1 - u0) * (v1 - v0) > cfg.refine_max_pixels for u0, v0, u1, v1 in windows]
        fine = [i for i, big in enumerate(large) if not big]
        coarse = [i for i, big in enumerate(large) if big]
        parts = []
        if fine:
            parts.append(_window_pixels(full, state.expected_full(ref), [windows[i] for i in fine],
                                        [chunk[i][1:6] for i in fine], s, full_sigma, full_threshold))
        if coarse:
            parts.append(_region_pixels(small, small_sq, [chunk[i][1:6] for i in coarse], small_threshold))
        values, magnitude, xs, ys, counts = (np.concatenate(p) for p in zip(*parts, strict=True))
        noise = np.repeat([full_noise, small_noise], [len(fine), len(coarse)])
        found_all = dict(zip(fine + coarse, _centres_of_groups(values, magnitude, xs, ys, counts, noise,
                                                               cfg.lobe_fraction, cfg.extent_fraction), strict=True))
        for i, (candidate, (u0, v0, u1, v1), big) in enumerate(zip(chunk, windows, large, strict=True)):
            found = found_all[i]
            # the coarse mask's area is spread by the blur: the contact itself (its extent at full
            # resolution) must be large; a speck or a dust grain shifted with the membrane is not
            if found is None or found[4] * (s * s if big else 1) < cfg.min_area:
                continue
            touches = u0 == 0 or v0 == 0 or u1 == width or v1 == height
            score = math.sqrt(candidate[6]) / small_noise
            if big:
                contacts.append(_contact(found, candidate[1] * s, candidate[2] * s, s, small_threshold, score, touches))
            else:
                contacts.append(_contact(found, u0, v0, 1, full_threshold, score, touches))
            if len(contacts) >= cfg.max_contacts:
                break
    return contacts


def _small_difference(small_frame: np.ndarray, state: BackgroundModel,
                      cfg: DetectorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The blurred downscaled difference to the modelled background, its squared colour distance,
    the pixels over the threshold, and the threshold."""
    assert state.expected_small is not None, "fit the background model first"
    threshold = max(cfg.min_threshold, cfg.threshold_sigma * float(state.noise or 0.0))
    small = np.atleast_3d(_blur(_difference(small_frame, state.expected_small), cfg.blur_sigma))
    small_sq = _squared_norm(small)
    return small, small_sq, small_sq > threshold * threshold, threshold


def _full_to_small_noise(ref: NoContactReference, s: int, cfg: DetectorConfig) -> float:
    """Noise std of the blurred full-resolution difference relative to that of the blurred downscaled one.

    Measured on the reference frames when there are several; else the value for white noise
    (bilinear downscaling by an even factor averages 2x2 pixels, by an odd one picks a pixel).
    Real noise is correlated, so white noise overstates the full-resolution side: a safe threshold.
    """
    if ref.frame_count >= 2:
        small_noise = ref.small(s)[1]
        if small_noise > 0 and ref.noise_std > 0:
            return float(ref.noise_std * _blur_noise_factor(cfg.refine_blur_sigma)
                         / (small_noise * _blur_noise_factor(cfg.blur_sigma)))
    averaged = 0.5 if s % 2 == 0 else 1.0
    return _blur_noise_factor(cfg.refine_blur_sigma) / (averaged * _blur_noise_factor(cfg.blur_sigma))


def _contact(found: tuple, u0: int, v0: int, s: int, threshold: float, score: float, touches: bool) -> Contact:
    """A Contact from a blob's centre and moments in its window (origin u0, v0; s full pixels per pixel)."""
    cu, cv_, peak, _significant, extent, mxx, myy, mxy = found
    shift = (s - 1) / 2.0    # centre of window pixel i is full pixel i * s + (s - 1) / 2
    # the window's pixels are s x s squares: their own spread adds (s^2 - 1) / 12 per axis
    quantum = (s * s - 1) / 12.0
    mxx, myy, mxy = mxx * s * s + quantum, myy * s * s + quantum, mxy * s * s
    half_trace, det_root = 0.5 * (mxx + myy), math.hypot(0.5 * (mxx - myy), mxy)
    major, minor = half_trace + det_root, max(half_trace - det_root, 0.0)
    angle = 0.5 * math.atan2(2.0 * mxy, mxx - myy)
    confidence = max(0.0, 1.0 - threshold / peak) * (0.5 if touches else 1.0)
    return Contact(u=cu * s + shift + u0, v=cv_ * s + shift + v0, area=float(extent * s * s),
                   confidence=float(confidence), score=float(score), major_axis=4.0 * math.sqrt(major),
                   minor_axis=4.0 * math.sqrt(minor), angle=angle if angle > -math.pi / 2 else angle + math.pi)


Candidate = tuple[int, int, int, int, int, np.ndarray, float]   # signal area, x0, y0, w, h, region, peak^2
# centre u, v in the window, peak distance, pixels over the threshold, extent (pixels), central second
# moments xx, yy, xy
Found = tuple[float, float, float, int, int, float, float, float] | None


def _candidates_of(above: np.ndarray, small_sq: np.ndarray, s: int, cfg: DetectorConfig) -> list[Candidate]:
    mask = above.astype(np.uint8)
    if cfg.close_size > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (cfg.close_size, cfg.close_size))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    # contours are ~10x cheaper than connectedComponentsWithStats on this small mask
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    inside = above
    band = math.ceil(cfg.border / s)
    if band > 0:
        # the image's edge (lens rim, membrane clamp, LED glare) changes with the slightest shift:
        # a blob must be large and strong enough without it (but keeps its pixels there)
        inside = above.copy()
        inside[:band], inside[-band:], inside[:, :band], inside[:, -band:] = False, False, False, False
    return _candidates(contours, inside, small_sq, s * s * 1.0, cfg.min_area)


def _candidates(contours: Sequence[np.ndarray], above: np.ndarray, small_sq: np.ndarray, pixel_area: float,
                min_area: float) -> list[Candidate]:
    """Blobs of the closed mask, largest signal first, without those below `min_area`, with their peak.

    Area and peak count only pixels of `above` (over the threshold, away from the border): closing
    must not turn scattered noise into a blob.
    A blob whose whole bounding box is smaller than `min_area` is dropped before it is drawn
    (textured frames have dozens of such specks). Outer contours filled do not overlap, so one
    label image serves all blobs.
    """
    labels = np.zeros(above.shape, np.int32)
    boxes = []
    for contour in contours:
        x0, y0, w, h = cv2.boundingRect(contour)
        if w * h * pixel_area < min_area:
            continue
        boxes.append((x0, y0, w, h))
        cv2.drawContours(labels, [contour], -1, len(boxes), thickness=-1)
    if not boxes:
        return []
    signal = np.bincount(labels[above], minlength=len(boxes) + 1)
    candidates = []
    for i, (x0, y0, w, h) in enumerate(boxes, 1):
        if signal[i] * pixel_area >= min_area:
            region = (labels[y0:y0 + h, x0:x0 + w] == i).view(np.uint8)
            peak = float(small_sq[y0:y0 + h, x0:x0 + w][region.view(bool) & above[y0:y0 + h, x0:x0 + w]].max())
            candidates.append((int(signal[i]), x0, y0, w, h, region, peak))
    candidates.sort(key=lambda c: -c[0])
    return candidates


Pixels = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]   # see _centres_of_groups


def _region_pixels(small: np.ndarray, small_sq: np.ndarray, blobs: Sequence[tuple], threshold: float) -> Pixels:
    """The pixels of large blobs on the downscaled difference that exceed the threshold."""
    picks = []
    channels = small.shape[2]
    for x0, y0, w, h, region in blobs:
        score = np.sqrt(small_sq[y0:y0 + h, x0:x0 + w])
        index = np.flatnonzero(region.view(bool) & (score > threshold))
        ys, xs = np.divmod(index, w)
        picks.append((np.ascontiguousarray(small[y0:y0 + h, x0:x0 + w]).reshape(-1, channels).take(index, axis=0),
                      score.ravel().take(index), xs, ys))
    return (np.concatenate([p[0] for p in picks]), np.concatenate([p[1] for p in picks]),
            np.concatenate([p[2] for p in picks]), np.concatenate([p[3] for p in picks]),
            np.array([len(p[1]) for p in picks]))


def _window_pixels(full: np.ndarray, reference: np.ndarray,
                   windows: Sequence[tuple[int, int, int, int]], blobs: Sequence[tuple], s: int,
                   sigma: float, threshold: float) -> Pixels:
    """The pixels of each blob's mask that exceed the threshold on the blurred full-resolution
    difference to `reference` (the modelled background) in the blob's window, all windows in one
    pass over a mosaic of the windows.

    Per blob, a dozen small numpy/OpenCV calls cost ~0.1 ms in call overhead alone. Instead the
    windows are copied into one image (shelf-packed), each cropped to its blob's mask plus the
    blur's reach and padded by repeating the window's edge pixels where the window ends: the blur
    then sees exactly what blurring each window on its own with BORDER_REPLICATE sees, so the
    centres equal the per-window refinement. Differencing, blur, threshold and pixel selection
    run once on the mosaic; pixels are grouped by window through the labelled masks.
    """
    channels = full.shape[2]
    # Only the blob's mask matters: its upscaled box grown by the dilation's reach, inside the
    # window. Around that, the blur's reach. Windows are padded in the mosaic by at least both
    # reaches, so dilated masks stay out of other windows.
    grow = (s + 1) // 2
    pad = max(_ksize(sigma) // 2 if sigma > 0 else 0, grow)
    boxes = [(max(u0, x0 * s - grow), max(v0, y0 * s - grow),
              min(u1, (x0 + w) * s + grow), min(v1, (y0 + h) * s + grow))
             for (u0, v0, u1, v1), (x0, y0, w, h, _) in zip(windows, blobs, strict=True)]
    places, mosaic_shape = _pack([(b1 - b0 + 2 * pad, a1 - a0 + 2 * pad) for a0, b0, a1, b1 in boxes])
    frame = np.zeros(mosaic_shape + (channels,), full.dtype)
    expected = np.zeros(mosaic_shape + (channels,), np.float32)
    # each blob's mask, labelled 1 + its window's index: after dilation it also says whose a pixel is
    region = np.zeros(mosaic_shape, np.uint8 if len(windows) < 255 else np.uint16)
    clipped = []
    for i, ((u0, v0, u1, v1), (a0, b0, a1, b1), (x0, y0, w, h, small_region), (r0, c0)) in enumerate(zip(
            windows, boxes, blobs, places, strict=True)):
        tile = (slice(r0, r0 + b1 - b0 + 2 * pad), slice(c0, c0 + a1 - a0 + 2 * pad))
        if a0 - pad >= u0 and b0 - pad >= v0 and a1 + pad <= u1 and b1 + pad <= v1:     # the usual case
            frame[tile] = full[b0 - pad:b1 + pad, a0 - pad:a1 + pad]
            expected[tile] = reference[b0 - pad:b1 + pad, a0 - pad:a1 + pad]
        else:
            frame[tile] = _replicate_crop(full, (a0 - pad, b0 - pad, a1 + pad, b1 + pad), (u0, v0, u1, v1))
            expected[tile] = _replicate_crop(reference, (a0 - pad, b0 - pad, a1 + pad, b1 + pad), (u0, v0, u1, v1))
        up = cv2.resize(small_region, (w * s, h * s), interpolation=cv2.INTER_NEAREST)
        up = up[: v1 - y0 * s, : u1 - x0 * s]     # the window clips the blob's box
        ry, rx = r0 + pad + y0 * s - b0, c0 + pad + x0 * s - a0
        np.multiply(up, i + 1, out=region[ry:ry + up.shape[0], rx:rx + up.shape[1]], casting="unsafe")
        if (a0, b0, a1, b1) != (x0 * s - grow, y0 * s - grow, (x0 + w) * s + grow, (y0 + h) * s + grow):
            clipped.append((r0, c0, b1 - b0 + 2 * pad, a1 - a0 + 2 * pad))
    # the same per-pixel arithmetic as refining each window on its own
    diff = np.atleast_3d(_blur(_difference(frame, expected), sigma))
    score = cv2.sqrt(_squared_norm(diff))
    # the dilation reaches no further than the box grown by `grow`: only where the window cut that
    # box does the dilated mask spill past the window's edge, into the window's padding
    owner = cv2.dilate(region, np.ones((s + 1, s + 1), np.uint8))
    for r0, c0, tile_h, tile_w in clipped:
        tile = owner[r0:r0 + tile_h, c0:c0 + tile_w]
        tile[:pad], tile[tile_h - pad:], tile[:, :pad], tile[:, tile_w - pad:] = 0, 0, 0, 0
    owner *= score > threshold
    # flat indices: np.nonzero and 2-D fancy indexing cost ~4x more
    index = np.flatnonzero(owner)
    # group the pixels by window (stable: row-major order within each window)
    label = owner.ravel().take(index)
    order = np.argsort(label, kind="stable")          # radix sort on the small labels
    index, window = index.take(order), label.take(order).astype(np.intp) - 1
    ys, xs = np.divmod(index, mosaic_shape[1])
    # mosaic position -> position in the blob's window
    placed = list(zip(places, windows, boxes, strict=True))
    shift_x = np.array([c0 + pad - (a0 - u0) for (_, c0), (u0, *_), (a0, *_) in placed])
    shift_y = np.array([r0 + pad - (b0 - v0) for (r0, _), (_, v0, *_), (_, b0, *_) in placed])
    return (diff.reshape(-1, channels).take(index, axis=0), score.ravel().take(index),
            xs - shift_x.take(window), ys - shift_y.take(window), np.bincount(window, minlength=len(windows)))


def _replicate_crop(image: np.ndarray, box: tuple[int, int, int, int], bounds: tuple[int, int, int, int]) -> np.ndarray:
    """image[box] (u0, v0, u1, v1), where the part of `box` outside `bounds` repeats the edge pixels of `bounds`."""
    u0, v0, u1, v1 = box
    b_u0, b_v0, b_u1, b_v1 = bounds
    inner = image[max(v0, b_v0):min(v1, b_v1), max(u0, b_u0):min(u1, b_u1)]
    top, left = max(0, b_v0 - v0), max(0, b_u0 - u0)
    bottom, right = max(0, v1 - b_v1), max(0, u1 - b_u1)
    if top or left or bottom or right:
        return np.atleast_3d(cv2.copyMakeBorder(inner, top, bottom, left, right, cv2.BORDER_REPLICATE))
    return inner


def _pack(sizes: Sequence[tuple[int, int]]) -> tuple[list[tuple[int, int]], tuple[int, int]]:
    """Shelf packing of (height, width) boxes: columns of stacked boxes, widest first.

    Returns each box's (row, column) and the mosaic's (height, width). Columns are about as tall
    as the mosaic is wide, so little of the mosaic is left empty.
    """
    limit = max(max(h for h, _ in sizes), int(math.sqrt(sum(h * w for h, w in sizes))))
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i][1])
    shelves: list[tuple[int, int, list[int]]] = []
    places: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    fill = 0
    for i in order:
        h, w = sizes[i]
        if not shelves or fill + h > limit:
            start = shelves[-1][1] if shelves else 0
            shelves.append((start, start + w, []))
            fill = 0
        places[i] = (fill, shelves[-1][0])
        shelves[-1][2].append(i)
        fill += h
    height = max(sum(sizes[i][0] for i in members) for _, _, members in shelves)
    return places, (height, shelves[-1][1])


def _centres_of_groups(values: np.ndarray, magnitude: np.ndarray, x: np.ndarray, y: np.ndarray,
                       counts: np.ndarray, noise: np.ndarray, lobe_fraction: float = 0.0,
                       extent_fraction: float = 0.0) -> list[Found]:
    """Colour-aware centres and shapes of several blobs from their selected pixels, in one vectorised pass.

    The pixels of blob i are the i-th run of `counts[i]` entries of: signed changes `values`
    (n, C), colour distance `magnitude` (n,) and position `x`, `y` in the blob's window; `noise`
    is the noise std of each blob's difference image. Per channel, the centre is the midpoint of
    the brightening and the darkening lobe's centroids; the channels are weighted by the weaker
    lobe's mass, and those without two real lobes left out. A blob without any such channel falls
    back to its magnitude-weighted centroid.

    Each lobe's centroid uses only the lobe's core, weighted by how far it exceeds
    `lobe_fraction` of the lobe's own peak: a lobe scaled by any gain keeps its centroid, and the
    faint broad halo a real membrane shows around a press (and a shading change around it) stays
    out of the centre. The shape is the second moments of the pixels whose colour distance
    exceeds `extent_fraction` of the blob's peak.
    """
    found: list[Found] = [None] * len(counts)
    present = np.flatnonzero(counts)
    if present.size == 0:
        return found
    npix = counts[present]
    starts = np.concatenate(([0], np.cumsum(npix)[:-1]))
    channels = values.shape[1]
    x = x.astype(np.float64)
    y = y.astype(np.float64)
    # lobe masses (one row per lobe and channel, ~3x faster than pixel-major), then their cores
    lobes = np.empty((2 * channels, values.shape[0]), np.float64)
    np.maximum(values.T, 0.0, out=lobes[:channels])                 # brightening | darkening
    np.maximum(-values.T, 0.0, out=lobes[channels:])
    raw_mass = np.add.reduceat(lobes, starts, axis=1).T.tolist()     # (k, 2C)
    if lobe_fraction > 0:
        cut = np.maximum.reduceat(lobes, starts, axis=1) * lobe_fraction
        lobes -= np.repeat(cut, npix, axis=1)
        np.maximum(lobes, 0.0, out=lobes)
    terms = np.empty((3,) + lobes.shape, np.float64)
    terms[0] = lobes
    np.multiply(lobes, x, out=terms[1])
    np.multiply(lobes, y, out=terms[2])
    sums = np.add.reduceat(terms, starts, axis=2)                   # (3, 2C, k)
    peaks = np.maximum.reduceat(magnitude, starts)
    shapes = _shapes(magnitude, x, y, starts, np.repeat(extent_fraction * peaks, npix))
    peak = peaks.tolist()
    npix_list = npix.tolist()
    # a few numbers per blob: plain Python beats a dozen numpy calls on tiny arrays
    mass, moment_x, moment_y = (part.T.tolist() for part in sums)
    floors = (3.0 * noise[present] * np.sqrt(npix.astype(np.float64))).tolist()
    lone = []
    for k, i in enumerate(present.tolist()):
        u = v = total = 0.0
        for c in range(channels):
            pos, neg = raw_mass[k][c], raw_mass[k][channels + c]
            weight = min(pos, neg)
            core_pos, core_neg = mass[k][c], mass[k][channels + c]
            # a channel counts when both lobes carry real signal, not just noise leaking through the mask
            if weight > 0.1 * max(pos, neg) and weight > floors[k] and core_pos > 0 and core_neg > 0:
                u += 0.5 * (moment_x[k][c] / core_pos + moment_x[k][channels + c] / core_neg) * weight
                v += 0.5 * (moment_y[k][c] / core_pos + moment_y[k][channels + c] / core_neg) * weight
                total += weight
        if total > 0.0:
            found[i] = (u / total, v / total, peak[k], npix_list[k]) + shapes[k]
        else:
            lone.append((k, i))
    if lone:
        core = magnitude.astype(np.float64) - np.repeat(lobe_fraction * peaks, npix)
        np.maximum(core, 0.0, out=core)
        core += 1e-12 * (magnitude > 0)      # a flat blob (all at its peak) keeps its plain centroid
        core_total = np.add.reduceat(core, starts)
        centre_u = np.add.reduceat(core * x, starts) / core_total
        centre_v = np.add.reduceat(core * y, starts) / core_total
        for k, i in lone:
            found[i] = (float(centre_u[k]), float(centre_v[k]), peak[k], npix_list[k]) + shapes[k]
    return found


def _shapes(magnitude: np.ndarray, x: np.ndarray, y: np.ndarray, starts: np.ndarray,
            floor: np.ndarray) -> list[tuple[int, float, float, float]]:
    """Per group: the number of pixels with magnitude >= floor, and their central second moments xx, yy, xy."""
    inside = (magnitude >= floor).astype(np.float64)
    ix, iy = inside * x, inside * y
    n, sx, sy, sxx, syy, sxy = np.add.reduceat(np.stack([inside, ix, iy, ix * x, iy * y, ix * y]), starts, axis=1)
    n = np.maximum(n, 1.0)
    mx, my = sx / n, sy / n
    out = np.stack([n, sxx / n - mx * mx, syy / n - my * my, sxy / n - mx * my]).T.tolist()
    return [(int(a), max(b, 0.0), max(c, 0.0), d) for a, b, c, d in out]


def _illumination(frame: np.ndarray, reference: np.ndarray, noise: float,
                  threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel gain and offset taking the reference to the frame, fitted on the background.

    LED drift or auto exposure changes the whole image by a few grey levels, which a threshold of
    a few noise std would report as one image-wide contact. The fit must not see the contacts: a
    median offset (subsampled) gives a first difference, whatever exceeds the threshold there is
    masked with a wide margin (a dent's faint tails correlate with the background's shading), and
    gain and offset are fitted by least squares on the remaining pixels.
    """
    # a quarter of the pixels is plenty (contiguous copies: strided 3-channel numpy arithmetic is slow)
    frame, reference = np.ascontiguousarray(frame[::2, ::2]), np.ascontiguousarray(reference[::2, ::2])
    channels = frame.shape[2]
    gain = np.ones(channels, np.float32)
    shift = _channel_medians(frame[::3, ::3] - reference[::3, ::3])
    residual = np.atleast_3d(cv2.subtract(cv2.subtract(frame, reference), _scalar(shift)))
    contact = (_squared_norm(residual) > threshold**2).astype(np.uint8)
    background = cv2.dilate(contact, np.ones((5, 5), np.uint8)) == 0
    limit = 4.0 * noise + 2.0
    for c in range(channels):
        background &= np.abs(residual[:, :, c]) < limit
    count = int(background.sum())
    if count < max(16, background.size // 4):     # mostly "contact": keep the robust offset only
        return gain, shift
    offset = np.zeros(channels, np.float32)
    index = np.flatnonzero(background)
    frame_bg = frame.reshape(-1, channels).take(index, axis=0)
    reference_bg = reference.reshape(-1, channels).take(index, axis=0)
    for c in range(channels):
        fi = frame_bg[:, c].astype(np.float64)
        ri = reference_bg[:, c].astype(np.float64)
        r_mean, f_mean = ri.sum() / count, fi.sum() / count
        r_centred = ri - r_mean
        variance = float((r_centred * r_centred).sum())
        g = float((r_centred * (fi - f_mean)).sum()) / variance if variance > 1e-6 * count else 1.0
        gain[c] = min(max(g, 0.5), 2.0)      # beyond this it is not drift: let the detector see it
        offset[c] = f_mean - gain[c] * r_mean
    return gain, offset


def _channel_medians(image: np.ndarray) -> np.ndarray:
    """np.median over all pixels per channel (same values), ~5x faster: one partition per channel row."""
    rows = np.ascontiguousarray(image.reshape(-1, image.shape[2]).T)
    n = rows.shape[1]
    k = n // 2
    if n % 2:
        return np.partition(rows, k, axis=1)[:, k]
    part = np.partition(rows, (k - 1, k), axis=1)
    return (part[:, k - 1] + part[:, k]) / 2


def detect_paper(image: np.ndarray, reference: NoContactReference | None,
                 config: DetectorConfig | None = None) -> list[Contact]:
    """The paper's pipeline: grey, Gaussian blur, fixed binarisation, findContours, moments centroid."""
    cfg = config or DetectorConfig(method="paper")
    frame = _as_float(image)
    grey = to_grey(frame, uint8=False)
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
        mxx, myy, mxy = m["mu20"] / m["m00"], m["mu02"] / m["m00"], m["mu11"] / m["m00"]
        half_trace, root = 0.5 * (mxx + myy), math.hypot(0.5 * (mxx - myy), mxy)
        angle = 0.5 * math.atan2(2.0 * mxy, mxx - myy)
        contacts.append(Contact(u=m["m10"] / m["m00"], v=m["m01"] / m["m00"], area=float(m["m00"]),
                                confidence=1.0, score=math.nan, major_axis=4.0 * math.sqrt(half_trace + root),
                                minor_axis=4.0 * math.sqrt(max(half_trace - root, 0.0)),
                                angle=angle if angle > -math.pi / 2 else angle + math.pi))
    contacts.sort(key=lambda c: -c.area)
    return contacts[: cfg.max_contacts]
