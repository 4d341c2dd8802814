"""A drone's camera process (``swarm-camera``): its rendered images, or a real camera's
frames, through the marker detector into the camera frames its agent reads (docs/camera.md).
"""
