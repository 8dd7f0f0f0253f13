"""Defects in a world height map: cracks, dents and bumps found, measured and placed in the map's frame
(docs/inspection.md). No rclpy here."""
from touchroller_perception.inspection.detect import inspect, inspect_height, inspect_intensity, inspect_region
from touchroller_perception.inspection.types import (
    KINDS,
    Finding,
    InspectionConfig,
    InspectionDiagnostics,
    InspectionResult,
    Kind,
)
from touchroller_perception.inspection.wkt import finding_wkt, parse_wkt

__all__ = ["KINDS", "Finding", "InspectionConfig", "InspectionDiagnostics", "InspectionResult", "Kind",
           "finding_wkt", "inspect", "inspect_height", "inspect_intensity", "inspect_region", "parse_wkt"]
