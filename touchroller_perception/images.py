"""The one grey conversion: any camera image (mono, BGR, BGRA; 8-bit, 16-bit or float) -> one channel."""
from __future__ import annotations

import cv2
import numpy as np


def to_grey(image: np.ndarray, *, uint8: bool = True) -> np.ndarray:
    """One channel of an HxW, HxWx1, HxWx3 (BGR) or HxWx4 (BGRA) image, weighted as OpenCV's BGR2GRAY.

    `uint8` True gives 8-bit grey (16-bit input keeps its high byte, float input is clipped to 0..255
    and rounded): what OpenCV's detectors and the map take. False keeps the values as float32 (the
    contact detector subtracts a float reference). ValueError (one line) for any other shape.
    """
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    elif array.ndim == 3 and array.shape[2] in (3, 4):
        if not uint8 or array.dtype.kind == "f":
            array = array.astype(np.float32, copy=False)
        array = cv2.cvtColor(array, cv2.COLOR_BGRA2GRAY if array.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    elif array.ndim != 2:
        raise ValueError(f"expected an HxW, HxWx3 or HxWx4 image, got shape {array.shape}")
    if not uint8:
        return array.astype(np.float32, copy=False)
    if array.dtype == np.uint16:
        return (array >> 8).astype(np.uint8)
    if array.dtype != np.uint8:
        return np.clip(np.rint(array), 0, 255).astype(np.uint8)
    return array
