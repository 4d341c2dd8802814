"""The rendered camera's pipeline (issue 45, point 5): its cost per frame, its accuracy, and
what frame rate six drones sustain on this machine.

    python benchmarks/bench_camera.py [--profile quick] [--out FILE]
    (or as the ``camera`` section of ``python benchmarks/run_all.py``)

- Stages: ``camera_frames`` random poses (a drone 2-7 m above the ground anywhere over the
  arena, one target anywhere under its field of view, the configured marker), rendered
  (``CameraRenderer.render``), encoded (JPEG), decoded (``cv2.imdecode``) and detected
  (``MarkerDetector.detect``: ArUco, sub-pixel corners, the planar pose), each timed alone
  (median and p99 in ms), for Case 1's camera (480 px) and the same with a lens
  (k1 = −0.15, k2 = 0.03, p1 = 0.001, p2 = −0.001) and at 320 px.
- Accuracy, on the same frames: the image-point error of each detection against the truth's
  (``ideal_image_point``): its standard deviation per axis (the σ_img the bearing model would
  need to match it), median and p99 of its norm in pixels; the detection probability by
  distance to the target and by its angle off the optical axis; identities read wrong (a
  marker read as another target: never allowed to pass) and targets in view but missed.
- Swarm: Case 1 with rendered cameras through the process swarm (six agents, six
  ``swarm-camera`` detectors, the world rendering), lockstep at 50, 25 and 10 frames per
  second (real-time factor: simulated s per wall s), and realtime at the same rates (late
  steps, the agents' CPU), each with the share of the frames the agents measured with (agent
  steps that measured a target, per drone and frame: lockstep is the reference) and the final
  estimate error. The bearing camera's runs are measured beside them, in the same run.
"""

from __future__ import annotations

import dataclasses
import itertools
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from common import (
    CONFIGS,
    PROFILES,
    Profile,
    SectionClock,
    fmt,
    new_table,
    progress,
    report_section,
    section_parser,
    stats,
)
from rich.table import Table
from swarm_probe import attempt_swarm

from swarm.models.camera import CameraParams, ideal_image_point
from swarm.scenario.config import ScenarioConfig, load_config, write_resolved_config
from swarm.vision.codec import encode_jpeg
from swarm.vision.detect import MarkerDetector
from swarm.vision.render import CameraRenderer

LENS = (-0.15, 0.03, 0.001, -0.001, 0.0)
RANGE_BINS_M = (2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0)
ANGLE_BINS_DEG = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0)
FRAME_RATES_HZ = (50.0, 25.0, 10.0)


def random_pose(rng: np.random.Generator, camera: CameraParams) -> tuple[np.ndarray, np.ndarray]:
    """A drone 2-7 m up anywhere over ±40 m, a target anywhere under its field of view."""
    drone = np.array([*rng.uniform(-40.0, 40.0, 2), rng.uniform(2.0, 7.0)])
    reach = np.tan(np.radians(camera.half_fov_deg)) * drone[2]
    target = np.array([*(drone[:2] + rng.uniform(-reach, reach, 2)), 0.0])
    return drone, target


def pipeline(camera: CameraParams, frames: int, seed: int = 45) -> dict[str, Any]:
    """Stage times and accuracy of ``frames`` random frames (module docstring)."""
    renderer = CameraRenderer(camera, 1)
    detector = MarkerDetector(camera, renderer.calibration, 1)
    focal_px = float(renderer.calibration.camera_matrix[0, 0])
    rng = np.random.default_rng(seed)
    times: dict[str, list[float]] = {"render": [], "encode": [], "decode": [], "detect": []}
    errors, sizes = [], []
    seen = []  # (distance, off-axis angle, in view, detected)
    wrong_ids = 0
    for _ in range(frames):
        drone, target = random_pose(rng, camera)
        t0 = time.perf_counter()
        image = renderer.render(drone, target[None, :], rng)
        t1 = time.perf_counter()
        data = encode_jpeg(image, camera.jpeg_quality)
        t2 = time.perf_counter()
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
        t3 = time.perf_counter()
        found = detector.detect(decoded)
        t4 = time.perf_counter()
        for name, start, end in (("render", t0, t1), ("encode", t1, t2), ("decode", t2, t3),
                                 ("detect", t3, t4)):
            times[name].append((end - start) * 1e3)
        sizes.append(len(data))
        ideal = ideal_image_point(drone, target, camera)
        relative = target - drone
        distance = float(np.linalg.norm(relative))
        angle = float(np.degrees(np.arccos(-relative[2] / distance)))
        hits = [d for d in found.detections if d.target == 0]
        wrong_ids += len(found.detections) - len(hits)
        seen.append((distance, angle, ideal is not None, bool(hits)))
        if hits and ideal is not None:
            errors.append(hits[0].image_point - ideal)
    error = np.array(errors).reshape(-1, 2)
    norms_px = np.linalg.norm(error, axis=1) * focal_px
    table = np.array(seen, dtype=float)
    in_view = table[table[:, 2] > 0]

    def rate(column: int, bins: tuple[float, ...]) -> list[dict[str, Any]]:
        out = []
        for low, high in itertools.pairwise(bins):
            chosen = in_view[(in_view[:, column] >= low) & (in_view[:, column] < high)]
            out.append({"from": low, "to": high, "n": int(chosen.shape[0]),
                        "detected": (float(chosen[:, 3].mean()) if chosen.shape[0] else None)})
        return out

    return {
        "resolution_px": camera.resolution_px, "distortion": list(camera.distortion),
        "frames": frames, "stage_ms": {name: stats(v) for name, v in times.items()},
        "jpeg_bytes": stats(sizes),
        "error": {"sigma_x": float(error[:, 0].std()) if len(error) else None,
                  "sigma_y": float(error[:, 1].std()) if len(error) else None,
                  "bias_x": float(error[:, 0].mean()) if len(error) else None,
                  "bias_y": float(error[:, 1].mean()) if len(error) else None,
                  "px": stats(norms_px)},
        "in_view": int(in_view.shape[0]), "detected": int(in_view[:, 3].sum()),
        "wrong_ids": wrong_ids,
        "by_distance_m": rate(0, RANGE_BINS_M), "by_angle_deg": rate(1, ANGLE_BINS_DEG),
    }


def swarm_runs(profile: Profile, out_dir: Path) -> list[dict[str, Any]]:
    """Case 1 in the process swarm, bearing and rendered cameras at each frame rate."""
    base = load_config(CONFIGS / "case1.toml").with_duration(profile.camera_swarm_duration_s)
    runs = []
    variants: list[tuple[str, float | None, ScenarioConfig]] = [("bearing", None, base)]
    for rate in profile.camera_frame_rates_hz:
        camera = dataclasses.replace(base.camera, model="rendered", frame_rate_hz=rate)
        variants.append(("rendered", rate, dataclasses.replace(base, camera=camera)))
    for mode in profile.camera_modes:
        for name, rate, config in variants:
            path = write_resolved_config(config, out_dir / f"{name}-{rate}.json")
            result = attempt_swarm(path, config, mode)
            mission = result.get("mission", {})
            frames = config.swarm.n_drones * config.n_steps // config.camera_steps_per_frame
            measured = result.get("measured_steps")
            errors = result.get("final_position_error_m")
            runs.append({"mode": mode, "camera": name, "frame_rate_hz": rate,
                         "real_time_factor": mission.get("real_time_factor"),
                         "frames_measured": None if measured is None else measured / frames,
                         "final_error_m": None if not errors else max(errors),
                         "late_fraction": result.get("late_fraction"),
                         "agent_cores": result.get("cpu", {}).get("agent_cores", {}),
                         "error": result.get("error")})
    return runs


def run(profile: Profile) -> dict[str, Any]:
    clock = SectionClock()
    case1 = load_config(CONFIGS / "case1.toml")
    camera = dataclasses.replace(case1.camera, model="rendered")
    cameras = [camera, dataclasses.replace(camera, distortion=LENS),
               dataclasses.replace(camera, resolution_px=320)]
    pipelines = []
    for cam in cameras:
        progress(f"camera pipeline: {cam.resolution_px} px, distortion {list(cam.distortion)}, "
                 f"{profile.camera_frames} frames")
        pipelines.append(pipeline(cam, profile.camera_frames))
    with tempfile.TemporaryDirectory(prefix="vigil-bench-camera-") as tmp:
        swarms = swarm_runs(profile, Path(tmp))
    return {"section": "camera", "profile": profile.name, "pipelines": pipelines,
            "swarm": swarms, **clock.done()}


def tables(result: dict[str, Any]) -> list[Table]:
    stages = new_table("camera: cost per frame [ms] (median / p99) and accuracy",
                       ["camera", "render", "encode", "decode", "detect", "JPEG [KiB]",
                        "σ_x", "σ_y", "error median / p99 [px]", "detected", "wrong ids"])
    for p in result["pipelines"]:
        lens = "lens" if any(p["distortion"]) else "pinhole"
        ms = p["stage_ms"]
        stages.add_row(
            f"{p['resolution_px']} px, {lens}",
            *(f"{fmt(ms[s]['median'], 2)} / {fmt(ms[s]['p99'], 2)}"
              for s in ("render", "encode", "decode", "detect")),
            fmt(p["jpeg_bytes"]["median"] / 1024, 1),
            fmt(p["error"]["sigma_x"], 5), fmt(p["error"]["sigma_y"], 5),
            f"{fmt(p['error']['px']['median'], 2)} / {fmt(p['error']['px']['p99'], 2)}",
            f"{p['detected']}/{p['in_view']}", str(p["wrong_ids"]))
    reach = new_table("camera: detection probability of a target in view",
                      ["camera", *(f"{b['from']:g}-{b['to']:g} m"
                                   for b in result["pipelines"][0]["by_distance_m"]),
                       *(f"{b['from']:g}-{b['to']:g}°"
                         for b in result["pipelines"][0]["by_angle_deg"])])
    for p in result["pipelines"]:
        lens = "lens" if any(p["distortion"]) else "pinhole"
        reach.add_row(f"{p['resolution_px']} px, {lens}",
                      *(fmt(b["detected"], 2) for b in p["by_distance_m"]),
                      *(fmt(b["detected"], 2) for b in p["by_angle_deg"]))
    swarm = new_table("camera: Case 1, six drones, process swarm",
                      ["mode", "camera", "frames/s", "real-time factor", "late steps",
                       "frames measured", "final error [m]", "agent cores (median)"])
    for r in result["swarm"]:
        swarm.add_row(r["mode"], r["camera"], fmt(r["frame_rate_hz"], 0),
                      fmt(r["real_time_factor"], 2),
                      fmt(None if r["late_fraction"] is None else 100 * r["late_fraction"],
                          1, " %"),
                      fmt(r.get("frames_measured"), 2), fmt(r.get("final_error_m"), 3),
                      fmt((r["agent_cores"] or {}).get("median"), 2))
    return [stages, reach, swarm]


def main(argv: list[str] | None = None) -> int:
    parser = section_parser(__doc__ or "", "camera.json")
    args = parser.parse_args(argv)
    return report_section(run(PROFILES[args.profile]), tables, "bench_camera.py", argv,
                          args.out)


if __name__ == "__main__":
    raise SystemExit(main())
