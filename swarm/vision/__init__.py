"""Pixels in the loop (docs/camera.md): a rendered downward camera, the marker detector that
turns its images into the image-plane points the agents use, and the calibration and frame
sources a real camera plugs into. OpenCV does the projection, distortion, rendering warps,
image coding and marker detection; this package only chooses and checks."""

import cv2

# One thread: a renderer or a detector shares the cores with the swarm's other processes (the
# world, the agents, the other detectors), as the step's BLAS does (the launcher's
# BLAS_THREAD_VARIABLES); OpenCV's own pool would only oversubscribe them. Results do not
# depend on it (each output pixel is computed alone).
cv2.setNumThreads(1)
