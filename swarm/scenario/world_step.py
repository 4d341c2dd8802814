"""What the world shows at step k: the targets where their trajectories put them, each
drone's camera frame (SPEC §2, §11) and, with radios of limited range, who hears whom
(``swarm.core.network.RadioRange``, docs/network.md). The in-process reference and the world
process both step it, so the world's step is written once.

Each drone's camera draws its image noise from its own stream (``swarm.scenario.setup``):
drone i sees the same frames whichever process renders them. With ``camera.model =
"rendered"`` the scene renders each drone's image on its frame steps (``swarm.vision``) and,
where asked, runs the marker detector on the encoded frame, as a drone's detector would.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swarm.core.drone_step import Detection
from swarm.core.network import RadioRange
from swarm.models.camera import detect
from swarm.scenario.config import ScenarioConfig
from swarm.scenario.setup import STREAM_CAMERA, stream
from swarm.vision.codec import encode_jpeg
from swarm.vision.detect import MarkerDetector
from swarm.vision.render import CameraRenderer

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SceneStep:
    """The scene at one step: the truth, and what each drone's camera saw of it."""

    step: int
    time_s: float
    target_positions_m: Array  # (M, 3)
    target_velocities_m_s: Array  # (M, 3)
    # What every frame carries of the targets' velocities (estimation model
    # "single_integrator"); None otherwise.
    communicated_velocities_m_s: Array | None
    detections: list[list[Detection]]  # per drone, each visible target with its noise
    # network.topology = "range": (N, N) bool, which drones hear each other at this step (from
    # the drones' true positions); None for the fixed graph.
    links: NDArray[np.bool_] | None = None
    # camera.model = "rendered", on a frame step: each drone's encoded frame (JPEG), and what
    # its detector rejected, by reason (empty where the detector did not run); None otherwise.
    images: list[bytes] | None = None
    rejected: list[Counter[str]] = field(default_factory=list)

    def radio_neighbours(self, drone: int) -> tuple[int, ...] | None:
        """The drones ``drone``'s radio hears at this step (None: the fixed graph)."""
        return None if self.links is None else tuple(np.flatnonzero(self.links[drone]).tolist())


class Scene:
    """The targets and the cameras of a run seeded ``seed``; ``at(k, positions)`` is step k
    seen from the drones at ``positions`` ((N, 3), world frame [m], the truth). Call it once
    per step, in order: each call draws the cameras' noise and steps the radio."""

    def __init__(self, config: ScenarioConfig, seed: int) -> None:
        self.dt_s = config.scenario.dt_s
        self.camera = config.camera
        self.trajectories = [t.build() for t in config.targets]
        self.cameras = [stream(seed, STREAM_CAMERA, i) for i in range(config.swarm.n_drones)]
        self.communicates_velocities = config.estimation.model == "single_integrator"
        self.radio = RadioRange(config.network) if config.network.ranged else None
        self.renderer = (CameraRenderer(config.camera, len(config.targets))
                         if config.camera.rendered else None)
        self.detector = (None if self.renderer is None else MarkerDetector(
            config.camera, self.renderer.calibration, len(config.targets)))
        self.steps_per_frame = config.camera_steps_per_frame

    def at(self, step: int, drone_positions: Array, *, detect_markers: bool = True
           ) -> SceneStep:
        """Step ``step``. A rendered camera's frames are detected here unless
        ``detect_markers`` is False (the world process: each drone's detector runs apart)."""
        t = step * self.dt_s
        targets = np.array([traj.position(t) for traj in self.trajectories])
        target_velocities = np.array([traj.velocity(t) for traj in self.trajectories])
        images: list[bytes] | None = None
        rejected: list[Counter[str]] = []
        if self.renderer is None:
            detections = [detect(position, targets, self.camera, rng)
                          for position, rng in zip(drone_positions, self.cameras, strict=True)]
        elif step % self.steps_per_frame:
            detections = [[] for _ in self.cameras]  # no frame at this step
        else:
            images = [encode_jpeg(self.renderer.render(position, targets, rng),
                                  self.camera.jpeg_quality)
                      for position, rng in zip(drone_positions, self.cameras, strict=True)]
            detections = [[] for _ in self.cameras]
            if detect_markers and self.detector is not None:
                found = [self.detector.detect_encoded(image) for image in images]
                detections = [f.detections for f in found]
                rejected = [f.rejected for f in found]
        links = None if self.radio is None else self.radio.step(drone_positions)
        return SceneStep(step, t, targets, target_velocities,
                         target_velocities if self.communicates_velocities else None,
                         detections, links, images, rejected)
