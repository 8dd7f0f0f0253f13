"""Real GelSight presses with labelled centres, and how a contact detector scores on them.

The `taxim` wheel (MIT; a pinned test dependency) ships the calibration data of two real sensors:
`taxim/calib/<sensor>/dataPack.npz` holds `f0` (the no-contact frame, 480x640 bgr8), `imgs` (one
ball press per frame), `touch_center` ((u, v) pixel centre of each press, labelled by hand) and
`touch_radius` (pixels); `params.json` holds `sensor.pixmm` (mm per pixel).

* `gelsight_mini`: 24 presses. The detector's knobs are tuned on its even presses (`TUNING`), and
  reported on all, on the tuning half and on the held-out odd half separately.
* `gelsight`: 48 presses of an older GelSight, never tuned on: a validation set.

`score(presses, config)` runs a detector as a stream would (the one background frame is the
reference, then the presses in order) and matches its contacts to the labels: a press is found
when a contact's centre lies inside the labelled disc (the nearest such contact is the match);
every other contact in the frame is a false contact.
"""
from __future__ import annotations

import dataclasses
import importlib.resources
import json
import math
import time
from collections.abc import Sequence

import numpy as np

from touchroller_perception.contacts import Contact, ContactDetector, DetectorConfig

SENSORS = ("gelsight_mini", "gelsight")
TUNING_SENSOR = "gelsight_mini"


@dataclasses.dataclass(frozen=True)
class PressSet:
    """One sensor's no-contact frame and labelled presses."""

    sensor: str
    background: np.ndarray     # HxWx3 uint8, bgr
    presses: np.ndarray        # NxHxWx3 uint8
    centres: np.ndarray        # Nx2 float, (u, v) px
    radii: np.ndarray          # N float, px
    mm_per_pixel: float

    def __len__(self) -> int:
        return len(self.presses)

    @property
    def tuning(self) -> list[int]:
        """The presses the knobs may be tuned on: the even ones."""
        return list(range(0, len(self), 2))

    @property
    def held_out(self) -> list[int]:
        return list(range(1, len(self), 2))


def available() -> bool:
    try:
        return (importlib.resources.files("taxim") / "calib" / TUNING_SENSOR / "dataPack.npz").is_file()
    except ModuleNotFoundError:
        return False


def load_presses(sensor: str = TUNING_SENSOR) -> PressSet:
    """The presses of `sensor` (one of SENSORS) from the taxim wheel; ModuleNotFoundError without it."""
    if sensor not in SENSORS:
        raise ValueError(f"sensor must be one of {SENSORS}, got {sensor!r}")
    folder = importlib.resources.files("taxim") / "calib" / sensor
    with (folder / "dataPack.npz").open("rb") as handle, np.load(handle) as data:
        background, presses = data["f0"], data["imgs"]
        centres, radii = data["touch_center"].astype(np.float64), data["touch_radius"].astype(np.float64)
    params = json.loads((folder / "params.json").read_text())
    return PressSet(sensor, background, presses, centres, radii, float(params["sensor"]["pixmm"]))


@dataclasses.dataclass(frozen=True)
class PressResult:
    """One press: the matched contact (None if missed), its centre error, the other contacts, the time."""

    index: int
    contact: Contact | None
    error_px: float            # nan when missed
    false_contacts: int
    seconds: float             # best of the repeats


@dataclasses.dataclass(frozen=True)
class Scorecard:
    sensor: str
    method: str
    mm_per_pixel: float
    results: tuple[PressResult, ...]

    def subset(self, indices: Sequence[int]) -> Scorecard:
        keep = set(indices)
        return dataclasses.replace(self, results=tuple(r for r in self.results if r.index in keep))

    @property
    def presses(self) -> int:
        return len(self.results)

    @property
    def found(self) -> int:
        return sum(r.contact is not None for r in self.results)

    @property
    def errors_px(self) -> np.ndarray:
        return np.array([r.error_px for r in self.results if r.contact is not None])

    def error_px(self, percentile: float) -> float:
        errors = self.errors_px
        return float(np.percentile(errors, percentile)) if errors.size else math.nan

    @property
    def median_px(self) -> float:
        return self.error_px(50)

    @property
    def p90_px(self) -> float:
        return self.error_px(90)

    @property
    def false_contacts(self) -> int:
        return sum(r.false_contacts for r in self.results)

    @property
    def false_per_frame(self) -> float:
        return self.false_contacts / max(self.presses, 1)

    @property
    def median_ms(self) -> float:
        return 1e3 * float(np.median([r.seconds for r in self.results]))


def match(contacts: Sequence[Contact], centre: Sequence[float], radius: float) -> tuple[Contact | None, float, int]:
    """The contact nearest the labelled centre among those inside the disc, its error, and how many others."""
    inside = [(math.hypot(c.u - centre[0], c.v - centre[1]), i) for i, c in enumerate(contacts)]
    inside = [(d, i) for d, i in inside if d <= radius]
    if not inside:
        return None, math.nan, len(contacts)
    error, best = min(inside)
    return contacts[best], error, len(contacts) - 1


def score(presses: PressSet, config: DetectorConfig | None = None, indices: Sequence[int] | None = None,
          repeats: int = 0) -> Scorecard:
    """Runs one detector over the presses (reference: the background frame alone) and matches the labels.

    The contacts come from one pass over the presses in order, as a stream would see them. With
    `repeats` > 0, a second detector times each frame that many times and keeps the fastest (a
    timing that a shared machine disturbs less); without, the time is that of the scoring pass.
    """
    config = config or DetectorConfig()
    order = list(indices) if indices is not None else list(range(len(presses)))
    detector = _detector(presses, config)
    results = []
    for i in order:
        start = time.perf_counter()
        contacts = detector.detect(presses.presses[i])
        seconds = time.perf_counter() - start
        contact, error, false = match(contacts, presses.centres[i], presses.radii[i])
        results.append(PressResult(int(i), contact, error, false, seconds))
    if repeats > 0:
        timer = _detector(presses, config)
        results = [dataclasses.replace(r, seconds=_best_time(timer, presses.presses[r.index], repeats))
                   for r in results]
    return Scorecard(presses.sensor, config.method, presses.mm_per_pixel, tuple(results))


@dataclasses.dataclass(frozen=True)
class StreamTime:
    """Time per frame of a detector running over all presses in order, as a stream: the background
    model's refits (every few frames, and after a large change) are included, spread over the frames."""

    cpu_ms: float     # CPU time of the thread per frame, best pass: what the detector costs on one core
    wall_ms: float    # wall time per frame, best pass: adds whatever else the machine ran meanwhile
    passes: int


def stream_time(presses: PressSet, config: DetectorConfig | None = None, passes: int = 10) -> StreamTime:
    """Best of `passes` runs of one detector over the presses in order (one reference frame).

    CPU time (`time.thread_time`) excludes the time the thread waits while other processes run, which
    on a shared machine dominates the wall time; it still includes refits, cache misses and every
    numpy/OpenCV call of the frame (OpenCV on the calling thread: `cv2.setNumThreads(1)`).
    """
    detector = _detector(presses, config or DetectorConfig())
    cpu, wall = math.inf, math.inf
    for _ in range(passes):
        start_wall, start_cpu = time.perf_counter(), time.thread_time()
        for frame in presses.presses:
            detector.detect(frame)
        cpu = min(cpu, time.thread_time() - start_cpu)
        wall = min(wall, time.perf_counter() - start_wall)
    n = max(len(presses), 1)
    return StreamTime(1e3 * cpu / n, 1e3 * wall / n, passes)


def _detector(presses: PressSet, config: DetectorConfig) -> ContactDetector:
    detector = ContactDetector(config, reference_frames=1)
    detector.set_reference([presses.background])
    return detector


def _best_time(detector: ContactDetector, image: np.ndarray, repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        detector.detect(image)
        best = min(best, time.perf_counter() - start)
    return best
