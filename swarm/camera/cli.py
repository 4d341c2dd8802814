"""``swarm-camera``: one drone's detector process (``swarm.camera.process``); launch-swarm
starts one per drone when ``camera.model = "rendered"``."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from swarm.children import follow_parent
from swarm.errors import run_main

PROG = "swarm-camera"


def main(argv: Sequence[str] | None = None) -> int:
    follow_parent(PROG)  # started by launch-swarm: die with it (swarm.children)
    argv = sys.argv[1:] if argv is None else list(argv)
    return run_main(PROG, lambda: _main(argv))


def _main(argv: list[str]) -> int:
    from swarm.camera.process import CameraOptions, CameraProcess
    from swarm.net.session import check_tls_endpoints, local_endpoint
    from swarm.scenario.cli_common import (
        OneLineParser,
        UsageError,
        add_run_arguments,
        load_scenario,
        terminate_on_sigterm,
    )

    parser = OneLineParser(prog=PROG, description=(
        "Run drone I's marker detector: the world's rendered images (or a camera's frames) "
        "in, the camera frames its agent reads out."))
    parser.add_argument("--id", type=int, required=True, metavar="I", help="drone id, 0..N-1")
    parser.add_argument("--config", required=True, metavar="FILE", help="scenario file")
    parser.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                        help="Zenoh endpoint of the world's router (default tcp/127.0.0.1:7447)")
    parser.add_argument("--source", default=None, metavar="URL",
                        help="take the pixels from this OpenCV VideoCapture source (a device "
                             "number, a video file, an image pattern such as frame_%%05d.png, "
                             "a GStreamer pipeline, an RTSP URL) instead of the world's images")
    parser.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                        help="that camera's OpenCV calibration file (YAML or XML: "
                             "image_width, image_height, camera_matrix, "
                             "distortion_coefficients); needed with --source")
    add_run_arguments(parser, run_id_help="the world's --run-id (default: vigil)")
    args = parser.parse_args(argv)
    if (args.source is None) != (args.calibration is None):
        raise UsageError("--source and --calibration go together: a camera's frames need its "
                         "calibration")
    config = load_scenario(args.config, args.duration)
    if not 0 <= args.id < config.swarm.n_drones:
        raise UsageError(f"--id {args.id} is out of range 0..{config.swarm.n_drones - 1} "
                         f"for {config.source}")
    if not config.camera.rendered:
        raise UsageError(f"{config.source}: camera.model is \"{config.camera.model}\": the "
                         f"world sends detections, there are no images to detect")
    check_tls_endpoints(args.connect or [], tls=config.security.enabled)
    terminate_on_sigterm()
    process = CameraProcess(CameraOptions(
        config=config, drone_id=args.id, run_id=args.run_id,
        connect=tuple(args.connect or [local_endpoint(7447, tls=config.security.enabled)]),
        mode=args.mode, log=lambda line: print(line, flush=True), source=args.source,
        calibration_file=args.calibration))
    try:
        return process.run()
    finally:
        process.close()


if __name__ == "__main__":
    sys.exit(main())
