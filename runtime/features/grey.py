"""Grey conversion: one for every detector (corridor, lights, boards)."""

from __future__ import annotations

import cv2
import numpy as np


def to_grey(image: np.ndarray) -> np.ndarray:
    """8-bit contiguous grey ``(H, W)`` of a grey, BGR or BGRA image.

    The one grey conversion every feature detector uses. 16-bit images keep their top
    8 bits (``>> 8``, as a camera's 10-16-bit readout scales); other dtypes are clipped
    to [0, 255].
    """
    img = image
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 3:
        if img.shape[2] == 1:
            return np.ascontiguousarray(img[:, :, 0])
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        return cv2.cvtColor(img, code)
    return np.ascontiguousarray(img)
