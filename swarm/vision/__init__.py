"""Pixels in the loop (docs/camera.md): a rendered downward camera, the marker detector that
turns its images into the image-plane points the agents use, and the calibration and frame
sources a real camera plugs into. OpenCV does the projection, distortion, rendering warps,
image coding and marker detection; this package only chooses and checks."""
