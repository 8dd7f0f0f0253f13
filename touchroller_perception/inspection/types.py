"""The inspection's configuration and results: thresholds with their units, a finding, the diagnostics."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Literal

Kind = Literal["crack", "dent", "bump"]
KINDS: tuple[Kind, ...] = ("crack", "dent", "bump")
Point = tuple[float, float]


@dataclass(frozen=True)
class InspectionConfig:
    """What counts as a defect. Lengths in metres of the map's frame; depths in the height map's unit (metres).

    The local surface is a Gaussian-weighted mean of the map (standard deviation `background_scale_m`)
    that leaves out, over `background_iterations` rounds, what lies `background_reject` noise sigmas off it
    (and at least `low_fraction` x `min_depth_m`);
    the residual is the map less that surface. A pixel seeds a finding where the residual passes the high
    threshold, max(`min_depth_m`, `noise_multiple` x the residual's robust sigma, `texture_multiple` x the
    texture's peaks: periodic textures such as a weave have peaks far above their sigma), and the finding grows
    over the pixels past `low_fraction` of it (hysteresis); pieces closer than `gap_m` are one finding.
    """

    background_scale_m: float = 2.5e-3      # sigma of the local surface: above a defect's size (dents <= 5 mm)
    background_iterations: int = 2          # rounds that leave the defects out of the local surface
    background_reject: float = 2.5          # noise sigmas off the surface that a round leaves out
    min_depth_m: float = 8e-6               # the high threshold never falls below this (texture, brushing)
    noise_multiple: float = 5.0             # ... nor below this many robust noise sigmas
    texture_multiple: float = 1.8           # ... nor below this many times the texture's peaks (99th percentile
                                            # of |residual| in blocks of 2 background scales, median over blocks)
    low_fraction: float = 0.5               # hysteresis: the low threshold as a share of the high one
    gap_m: float = 2e-4                     # pieces of one defect closer than this are joined
    crack_aspect: float = 3.0               # a crack is at least this many times longer than wide
    min_crack_length_m: float = 2e-3        # elongated depressions shorter than this are not reported
    min_branch_length_m: float = 1e-3       # side branches shorter (or shorter than 2 widths) are skeleton spurs
    min_blob_diameter_m: float = 3e-4       # dents/bumps: equivalent diameter of the region past half depth
    max_crack_width_m: float = 1.5e-3       # wider: surface form, not a crack (cracks are up to ~1 mm wide)
    max_blob_width_m: float = 3.5e-3        # dents/bumps: short axis at half depth above this is surface form
    edge_margin_m: float = 2e-4             # nothing is found this close to the map's edge, a NaN or the mask
    footprint_fwhm_px: float = 1.0          # the map's pixel footprint (FWHM, px) taken out of crack widths
    blur_fwhm_m: float = 0.0                # the map's point spread beyond its pixel (a sensor's gel, optics,
                                            # calibration smoothing, motion), FWHM: taken out of crack widths
                                            # and dent/bump diameters, their depths put back
    edge_band_m: float = 1e-3               # an elongated finding lying along the map's edge within this is an
                                            # edge artefact (a map's first and last rows curl), not reported
    intensity_blur_m: float = 1.5e-4        # intensity maps: |anomaly| smoothed by this (sigma), joining a
                                            # shading's bright and dark sides into one region
    min_intensity: float = 2.0              # intensity maps: the high threshold's floor, grey levels
    intensity_min_crack_m: float = 5e-3     # intensity maps: a shorter elongated anomaly is compact (a dent's
                                            # shaded sides are elongated along the light)
    noise_sample: int = 1_000_000           # at most this many pixels for the robust noise estimate

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value)):
                raise ValueError(f"InspectionConfig.{f.name} must be a finite number, got {value!r}")
        positive = ("background_scale_m", "noise_multiple", "crack_aspect", "background_reject")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"InspectionConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("min_depth_m", "texture_multiple", "gap_m", "max_crack_width_m", "max_blob_width_m",
                     "min_crack_length_m", "min_branch_length_m", "min_blob_diameter_m",
                     "edge_margin_m", "footprint_fwhm_px", "blur_fwhm_m", "edge_band_m", "intensity_blur_m",
                     "intensity_min_crack_m", "min_intensity"):
            if getattr(self, name) < 0:
                raise ValueError(f"InspectionConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.low_fraction <= 1:
            raise ValueError(f"InspectionConfig.low_fraction must be in (0, 1], got {self.low_fraction}")
        if self.background_iterations < 1 or self.noise_sample < 1000:
            raise ValueError("InspectionConfig.background_iterations must be >= 1 and noise_sample >= 1000")


@dataclass(frozen=True)
class Finding:
    """One defect. Coordinates in the map's frame (metres); `depth_m` positive for a depression, negative for
    a bump, NaN when the map has no depth (an intensity map). `polylines`: a crack's centreline (the trunk
    first, then its branches), each a list of (x, y); `polygon`: the outline of a dent or bump at half its
    depth (closed: the last point repeats the first). `length_m` is the trunk's length for a crack and the
    long axis at half depth for a dent or bump; `width_m` the median full width at half depth across a
    crack, the short axis of a dent or bump. `confidence` in [0, 1] rises with the depth over the noise
    (0.63 at the high threshold's noise multiple); a score, not a calibrated probability."""

    id: int
    kind: Kind
    x: float
    y: float
    length_m: float
    width_m: float
    depth_m: float
    area_m2: float
    confidence: float
    polylines: tuple[tuple[Point, ...], ...] = ()
    polygon: tuple[Point, ...] = ()

    @property
    def wkt(self) -> str:
        """The geometry as WKT: LINESTRING (a crack without branches), MULTILINESTRING (with branches),
        POLYGON (a dent or bump)."""
        from touchroller_perception.inspection.wkt import finding_wkt

        return finding_wkt(self)


@dataclass(frozen=True)
class InspectionDiagnostics:
    """What the thresholds were on this map (in the map's unit: metres for height)."""

    noise_sigma: float              # robust (MAD) sigma of the residual over the valid pixels
    texture_peak: float             # the texture's peaks (InspectionConfig.texture_multiple)
    high_threshold: float           # a finding's seed passes this
    low_threshold: float            # and grows over pixels past this
    valid_pixels: int               # pixels inspected (finite, unmasked, away from the edges)
    components: int                 # candidate regions after hysteresis, before classification
    dropped_short: int              # elongated depressions shorter than min_crack_length_m
    dropped_small: int              # compact regions below min_blob_diameter_m
    dropped_broad: int              # regions wider than max_crack_width_m / max_blob_width_m (surface form)
    dropped_shallow: int            # regions whose measured depth (a crack's median, a dent's smoothed peak)
                                    # stays below the high threshold
    dropped_edge: int = 0           # elongated regions along the map's edge (InspectionConfig.edge_band_m)


@dataclass(frozen=True)
class InspectionResult:
    findings: list[Finding]
    diagnostics: InspectionDiagnostics
