"""The perception node's parameter tables: each binds one of its configs (touchroller_bringup.ros_params).

DETECTOR_PARAMETERS (DetectorConfig), STITCHER_PARAMETERS (StitcherConfig), HEIGHT_PARAMETERS
(WorldHeightConfig), VIEW_PARAMETERS (TileConfig) and WORLD_FIELDS (`WorldSettings`, the world map's
parameters, which give the mapper its WorldMapConfig); a change of the stitcher's, the height map's or the
world map's starts a new map. PERCEPTION_FIELDS binds the node's own `PerceptionSettings` (the contacts'
frame, the reference's frames, where and how often the map goes out). The live findings' table is
touchroller_bringup.live_findings'.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from touchroller_bringup import names
from touchroller_bringup.ros_params import ParameterField, frame_id_problem
from touchroller_perception.contacts import METHODS
from touchroller_perception.world_map import WorldMapConfig

# parameter name -> (DetectorConfig field, description, min, max)
DETECTOR_PARAMETERS: dict[str, tuple[str, str, float | None, float | None]] = {
    "contacts.method": ("method", f"Detector: {' or '.join(METHODS)} (the paper's grey/threshold/moments)",
                        None, None),
    "contacts.threshold_sigma": ("threshold_sigma", "Threshold in multiples of the reference's measured noise",
                                 0.5, 100.0),
    "contacts.min_threshold": ("min_threshold", "Lowest threshold on the colour distance, grey levels", 0.0, 255.0),
    "contacts.downscale": ("downscale", "Candidate search on a 1/downscale image (refined at full size)", 1, 16),
    "contacts.min_area": ("min_area", "Smallest contact, pixels above threshold (full resolution)", 0.0, 1e6),
    "contacts.max_contacts": ("max_contacts", "Most contacts reported per frame", 1, 1000),
    "contacts.paper_threshold": ("paper_threshold", "Fixed grey threshold of the paper's pipeline", 0.0, 255.0),
    "contacts.compensate_illumination": ("compensate_illumination",
                                         "Fit a per-channel gain/offset to the reference (LED drift, exposure)",
                                         None, None),
    "contacts.background_sigma": ("background_sigma", "Scale of the smooth shading field removed from the "
                                  "difference, px (0 disables)", 0.0, 10000.0),
    "contacts.min_score": ("min_score", "Smallest contact peak, in noise std of the difference", 0.0, 1e6),
    "contacts.lobe_fraction": ("lobe_fraction", "Centre from each lobe's part above this fraction of its peak",
                               0.0, 0.95),
    "contacts.extent_fraction": ("extent_fraction", "A contact's area and ellipse: pixels above this fraction "
                                 "of its peak", 0.0, 0.95),
    "contacts.border": ("border", "Band along the image edges that cannot make a contact on its own, px",
                        0.0, 1000.0),
    "contacts.adapt_rate": ("adapt_rate", "Weight of a quiet frame blended into the reference every 8 frames "
                            "(0: fixed reference)", 0.0, 0.95),
}



# parameter name -> (StitcherConfig field, description, min, max); a change starts a new map
STITCHER_PARAMETERS: dict[str, tuple[str, str, float | None, float | None]] = {
    "map.method": ("method", "Stitching: default (subpixel keyframe registration) or paper (integer MAE search)",
                   None, None),
    "map.band_rows": ("band_rows", "Rows of the contact band used per frame (the paper: 70)", 8, 480),
    "map.search": ("search", "Largest shift per frame searched, pixels (the paper: 25)", 1, 200),
    "map.rectify": ("rectify", "Resample the band to membrane coordinates through the camera model", None, None),
    "map.subpixel": ("subpixel", "Subpixel registration and placement", None, None),
    "map.keyframes": ("keyframes", "Register against a keyframe (less drift) rather than the previous frame",
                      None, None),
    "map.keyframe_overlap": ("keyframe_overlap", "Take a new keyframe when the overlap falls below this",
                             0.05, 0.95),
    "map.motion_prior": ("motion_prior", "Search near the shift the recent velocity predicts first", None, None),
    "map.local_search": ("local_search", "Half-width of that first search, pixels", 0, 50),
    "map.background": ("background", "Divide out the flat field (what does not move with the surface)",
                       None, None),
    "map.lateral": ("lateral", "Also track shifts along the roller axis", None, None),
    "map.column_bin": ("column_bin", "Columns averaged together for registration (speed)", 1, 32),
    "map.highpass": ("highpass", "Box size of the high-pass filter before registration, pixels", 1, 99),
    "map.min_confidence": ("min_confidence", "Below this registration confidence the motion prior is used",
                           0.0, 1.0),
    "map.history": ("history", "Per-frame registration records kept (the newest)", 1, 1_000_000),
    "map.max_rows": ("max_rows", "Strip map: the most rows kept (0.1 mm each with the default geometry); a longer "
                     "map keeps the rows nearest the newest frame, drops the rest and says so on /diagnostics "
                     "(memory stays bounded however long frames come without a sweep); at least 8 x map.band_rows",
                     64, 10_000_000),
}


# parameter name -> (WorldHeightConfig field, description, min, max); a change starts a new map
HEIGHT_PARAMETERS: dict[str, tuple[str, str, float | None, float | None]] = {
    "map.height.band_depth": ("band_depth", "Height map: the rows integrated are those a press this deep reaches, m "
                              "(more than the scan presses: the rows beyond are the zero)", 1e-5, 0.0099),
    "map.height.outer_fraction": ("outer_fraction", "Height map: fraction of those rows at either end taken as "
                                  "undeformed", 0.02, 0.4),
    "map.height.min_indentation": ("min_indentation", "Height map: band pixels indented less are not in contact "
                                   "(no height there), m", 0.0, 1e-3),
    "map.height.min_weight": ("min_weight", "Height map: a cell has a height where its summed weight is at least "
                              "this", 1e-3, 100.0),
    "map.height.min_overlap": ("min_overlap", "Height map: cells two passes must share to be levelled against each "
                               "other", 10, 10_000_000),
    "map.height.axis_sigma": ("axis_sigma", "Height map: along the axis, variation slower than a Gaussian of this "
                              "sigma (px) comes from each column's slopes across the band (0: the 2-D solution)",
                              0.0, 200.0),
    "map.height.smoothing": ("smoothing", "Height map: the image's smoothing (Gaussian sigma, px) before the colour "
                             "features when a frame's slopes are read (the calibration may have used more)", 0.0, 20.0),
    "map.height.follow_arm": ("follow_arm", "Height map: raise each frame's relief by the roller's height above its "
                              "pressed height (the arm's pose); false: the press depth is taken as constant along a "
                              "pass", None, None),
    "map.height.resampling": ("resampling", "Height map: how a frame's relief goes onto the map grid: lanczos4 or "
                              "cubic (interpolated, times the weights placed bilinearly), linear (the weighted relief "
                              "splatted bilinearly as the intensity is: loses a fine relief's depth)", None, None),
    "map.height.slopes": ("slopes", "Height map: what a pixel's slope is when a frame is integrated: footprint (the "
                          "mean over the pixel's area, the height's difference across it) or centre (the slope at "
                          "its centre: reads a relief a few pixels across shallow)", None, None),
    "map.height.row_frames": ("row_frames", "Height map: take the band rows' static error (the press shape as the "
                              "model reads it, averaged over the frames mapped) out of each frame's relief once this "
                              "many frames are in (0: never)", 0, 1_000_000),
}

# parameter name -> (TileConfig field, description, min, max): the world map's live views
VIEW_PARAMETERS: dict[str, tuple[str, str, int, int]] = {
    "map.view_max_pixels": ("max_pixels", "World map: the most pixels of the view published on map (and of "
                            "the tiles on map_markers): the map is downsampled by 2, 4, ... to fit", 262_144,
                            100_000_000),
    "map.tile_px": ("tile_px", "World map: the side of a tile on map_markers, view pixels", 64, 2048),
}


@dataclass(frozen=True)
class WorldSettings:
    """The world map's parameters (WORLD_FIELDS): its frame, whether to map in it, and its WorldMapConfig."""

    world_frame: str = names.BASE_FRAME
    world: bool = True
    resolution: float = 1e-4
    bounds: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
    latency_estimate: bool = True
    register: bool = True
    photometric: str = ""
    reference: str = ""

    def __post_init__(self) -> None:
        problem = frame_id_problem("world_frame", self.world_frame)
        if problem:
            raise ValueError(problem)
        self.map_config()   # the mapper's own checks (bounds, resolution)

    def map_config(self) -> WorldMapConfig:
        """The live world map's config (frames waiting for the latency estimate are read provisionally)."""
        bounds = [float(v) for v in self.bounds]
        if len(bounds) != 4:
            raise ValueError(f"map.bounds is [x_min, y_min, x_max, y_max], got {bounds}")
        return WorldMapConfig(resolution=float(self.resolution),
                              bounds=None if not any(bounds) else (bounds[0], bounds[1], bounds[2], bounds[3]),
                              latency=None if self.latency_estimate else 0.0, register=bool(self.register),
                              provisional=True)


# world-map parameters: a change starts a new map
WORLD_FIELDS: dict[str, ParameterField] = {
    "world_frame": ParameterField("world_frame", "Frame of the world map: the robot's base, as the robot driver "
                                  "names it (frame_prefix does not apply)"),
    "map.world": ParameterField("world", "Map in world_frame when TF links it to touchroller_cylinder (else the "
                                "strip map along the roll)"),
    "map.resolution": ParameterField("resolution", "World map: metres per pixel", 1e-6, 0.01),
    "map.bounds": ParameterField("bounds", "World map: [x_min, y_min, x_max, y_max] in world_frame, m (the scan's "
                                 "rectangle and a margin); all 0: it grows with what is mapped", length=4),
    "map.latency_estimate": ParameterField("latency_estimate", "World map: estimate the camera's latency (what "
                                           "stamps still lag the exposure after camera.latency) from the "
                                           "image-registered motion against the arm's"),
    "map.register": ParameterField("register", "World map: register each pass against the earlier ones where they "
                                   "overlap"),
    "map.height.photometric": ParameterField("photometric", "World map: PHOTOMETRIC.npz of 'touchroller calibrate "
                                             "photometric'; with map.height.reference, also the height map on "
                                             "map_height (empty: none)"),
    "map.height.reference": ParameterField("reference", "World map: a no-contact image of the sensor for the height "
                                           "map"),
}
WORLD_PARAMETERS = tuple(WORLD_FIELDS)


@dataclass(frozen=True)
class PerceptionSettings:
    """The node's own parameters (PERCEPTION_FIELDS), no algorithm's config: the frame of the contacts it
    publishes, the frames of a new reference, the file a finished map is saved to and the map's rate."""

    contacts_frame_id: str = names.CYLINDER_FRAME
    reference_frames: int = 5
    save_path: str = ""
    publish_rate: float = 1.0

    def __post_init__(self) -> None:
        problem = frame_id_problem("contacts.frame_id", self.contacts_frame_id)
        if problem:
            raise ValueError(problem)


def check_save_path(settings: PerceptionSettings) -> None:
    """ValueError when map.save_path names something that is there and is no file (a folder)."""
    path = settings.save_path
    if path and os.path.exists(path) and not os.path.isfile(path):
        raise ValueError(f"map.save_path {path} exists and is not a regular file; give a PNG file name")


PERCEPTION_FIELDS: dict[str, ParameterField] = {
    "contacts.frame_id": ParameterField("contacts_frame_id", "frame_id of the published contact points (after "
                                        "frame_prefix)"),
    "reference.frames": ParameterField("reference_frames", "No-contact frames averaged into the reference", 1, 1000),
    "map.save_path": ParameterField("save_path", "PNG file the finished map is written to when a sweep ends (empty: "
                                    "not saved); a world map also writes map.yaml beside it (nav2 map_server "
                                    "format)"),
    "map.publish_rate": ParameterField("publish_rate", "Tactile map publishing rate, Hz (0 disables the map)",
                                       0.0, 100.0),
}
