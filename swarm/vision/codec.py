"""Camera frames as bytes: JPEG through ``cv2.imencode`` (the world's rendered frames on the
wire and in recordings; the detector decodes any format OpenCV reads)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from swarm.errors import VigilError


class ImageCodecError(VigilError, RuntimeError):
    """OpenCV could not encode a frame; one line."""


def encode_jpeg(image: NDArray[np.uint8], quality: int) -> bytes:
    """A greyscale or BGR frame as JPEG bytes at ``quality`` (1-100)."""
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ImageCodecError(f"OpenCV could not encode a {image.shape} {image.dtype} frame "
                              f"as JPEG")
    return bytes(buffer)
