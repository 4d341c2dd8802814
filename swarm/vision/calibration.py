"""A camera's calibration on disk, in OpenCV's own file format (``cv2.FileStorage``, YAML or
XML): ``image_width``, ``image_height``, ``camera_matrix`` (3 x 3) and
``distortion_coefficients`` (4, 5 or 8), the names OpenCV's calibration sample writes, so a
file from ``cv2.calibrateCamera`` (or a camera maker's) works as it is."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from swarm.vision.geometry import Calibration, CalibrationError


def write_calibration(path: Path, calibration: Calibration) -> None:
    """``calibration`` to ``path`` (.yaml, .yml or .xml)."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not storage.isOpened():
        raise CalibrationError(f"{path}: cannot write a calibration file there")
    try:
        storage.write("image_width", int(calibration.width_px))
        storage.write("image_height", int(calibration.height_px))
        storage.write("camera_matrix", calibration.camera_matrix)
        storage.write("distortion_coefficients", calibration.distortion.reshape(1, -1))
    finally:
        storage.release()


def read_calibration(path: Path) -> Calibration:
    """The calibration in ``path``; ``CalibrationError`` (one line naming the file and what is
    wrong) when it is missing, unreadable or incomplete."""
    if not Path(path).is_file():
        raise CalibrationError(f"{path}: no such calibration file")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # the parser's error (its binding may wrap it)
        raise CalibrationError(f"{path}: not an OpenCV calibration file (it does not "
                               f"parse)") from None
    if not storage.isOpened():
        raise CalibrationError(f"{path}: not an OpenCV calibration file")
    try:
        values = {}
        for name in ("image_width", "image_height", "camera_matrix",
                     "distortion_coefficients"):
            node = storage.getNode(name)
            if node.empty():
                raise CalibrationError(f"{path}: no {name}")
            values[name] = node.mat() if node.isMap() or node.isSeq() else node.real()
    finally:
        storage.release()
    matrix, distortion = values["camera_matrix"], values["distortion_coefficients"]
    if matrix is None or distortion is None:
        raise CalibrationError(f"{path}: camera_matrix and distortion_coefficients must be "
                               f"matrices")
    try:
        return Calibration(np.asarray(matrix, dtype=np.float64),
                           np.asarray(distortion, dtype=np.float64).reshape(-1),
                           int(values["image_width"]), int(values["image_height"]))
    except CalibrationError as err:
        raise CalibrationError(f"{path}: {err}") from None
