"""`jsve render`: a EuRoC-format sequence rendered along a real ground-truth trajectory, for ORB-SLAM3.

    jsve render --trajectory GT/V101_GT.txt --timestamps TS/V101.txt --imu IMU/V101.txt \\
                --texture V1_01_first95/mav0/cam0/data -o rendered/V1_01

A thin layer over jsve.render.render_sequence (docs/render.md); --scheduler runs the frames on an
embedded Dask cluster (default), a process pool or a running Dask cluster (docs/scaling.md).
"""

from __future__ import annotations

import argparse

from jsve.cli import _common as common
from jsve.cli._scheduler import add_scheduler_option

HELP = "render a EuRoC-format image + IMU + ground-truth sequence along a real trajectory (for ORB-SLAM3)"

_DESCRIPTION = """\
Render a EuRoC-format dataset that ORB-SLAM3 (e.g. Examples/Monocular-Inertial/mono_inertial_euroc with
EuRoC's Monocular-Inertial.yaml) reads as it reads a real EuRoC sequence:

  OUT/mav0/cam0/data/<t_ns>.png   752x480 grey, EuRoC cam0 intrinsics and radial-tangential distortion
  OUT/mav0/cam0/data.csv, sensor.yaml
  OUT/mav0/imu0/data.csv, sensor.yaml          200 Hz: --imu's real stream, else synthesised (ADIS16448)
  OUT/mav0/state_groundtruth_estimate0/data.csv body (IMU) pose, velocity and bias at the IMU stamps
  OUT/jsve_render.json                          manifest, written last (marks the dataset complete)

The world is a closed room a few metres beyond the trajectory with furniture that occludes (tables,
shelves, pillars, crates), textured with a non-periodic mosaic of randomly flipped and rotated crops of
the --texture photographs at 5 mm per texel (mip-mapped), seen with lens distortion, exposure motion
blur, vignetting, auto-exposure gain changes and sensor noise. Without --texture the texture is a
procedural pattern (not photographic). Deterministic under --seed; resumable (re-run the same command:
frames already rendered are kept; a finished OUT is skipped). To score ORB-SLAM3's trajectory, use
OUT/mav0/state_groundtruth_estimate0/data.csv (--gt-format euroc): in inertial modes ORB-SLAM3 saves
body (IMU) poses, as that file holds.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help=HELP, description=_DESCRIPTION, formatter_class=common.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--trajectory",
        required=True,
        metavar="GT.txt",
        help="ORB-SLAM3's EuRoC left-camera ground truth, <SEQ>_GT.txt (evaluation/Ground_truth/"
        "EuRoC_left_cam/; its rotations are stored conjugated, which jsve undoes: docs/render.md)",
    )
    p.add_argument(
        "--timestamps",
        required=True,
        metavar="TS.txt",
        help="frame stamps in ns, one per line (ORB-SLAM3's EuRoC_TimeStamps/<SEQ>.txt) or a EuRoC "
        "cam0/data.csv; frames outside the trajectory's time span are dropped",
    )
    p.add_argument(
        "--imu",
        metavar="IMU.txt",
        help="a real EuRoC imu0 CSV to use (ORB-SLAM3's EuRoC_IMU/<SEQ>.txt); default: synthesised from the "
        "trajectory with the ADIS16448 noise model",
    )
    p.add_argument(
        "--imu-noise",
        choices=("in-flight", "datasheet"),
        default="in-flight",
        help="noise model of a synthesised IMU (without --imu): 'in-flight' adds to the ADIS16448 datasheet "
        "noise and bias walk the correlated errors that make dead reckoning drift as the real V1_01 stream "
        "drifts against its ground truth; 'datasheet' is the sensor at rest only, an IMU consistent with "
        "the rendered images (docs/render.md, 'Which IMU'). Default: in-flight",
    )
    p.add_argument(
        "--texture",
        metavar="DIR",
        help="folder of photographs for the wall and furniture texture (e.g. real EuRoC cam0 frames); "
        "default: a procedural, corner-rich pattern",
    )
    common.add_output_option(p, metavar="OUT", required=True, help="dataset folder to write")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="N",
        help="seed of the room, texture, IMU noise, gain and image noise",
    )
    p.add_argument(
        "--frames",
        metavar="A:B",
        help="render only frames A to B-1 of those kept, e.g. 0:600 (default: every frame)",
    )
    common.add_workers_option(p, "processes rendering frames", default=2)
    add_scheduler_option(p, "--trajectory, --texture and OUT")
    p.add_argument(
        "--exposure-ms", type=float, default=8.0, metavar="MS", help="exposure time for motion blur, ms"
    )
    p.add_argument(
        "--cars", type=int, default=0, metavar="N", help="car-sized boxes moving through the room (default 0)"
    )
    p.add_argument(
        "--pedestrians",
        type=int,
        default=0,
        metavar="N",
        help="pedestrian-sized columns moving through the room (default 0)",
    )
    p.add_argument(
        "--parked",
        default="0",
        metavar="K|all",
        help="how many of the objects stand still (cars first), or 'all': the same scene with every object "
        "parked where it stands at the start (default 0)",
    )
    p.add_argument(
        "--room-margin",
        type=float,
        metavar="M",
        help="walls this far beyond the camera centres' horizontal extent, m (default 3, or 6 with objects: "
        "their paths keep 2 m from every camera centre)",
    )
    p.add_argument("--force", action="store_true", help="replace an OUT rendered with another configuration")
    common.add_progress_option(p)
    common.add_yes_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from jsve.io._resume import StaleOutputError
    from jsve.io._scheduler import check_scheduler
    from jsve.render import RenderConfig, SceneConfig, render_sequence
    from jsve.render._sequence import sequence_size

    if args.workers < 1:
        return common.fail("render", "--workers must be >= 1")
    if args.exposure_ms < 0:
        return common.fail("render", "--exposure-ms must be >= 0")
    if args.imu and args.imu_noise != "in-flight":
        return common.fail("render", "--imu-noise describes a synthesised IMU; it cannot go with --imu")
    from jsve.sim import ImuNoise

    noise = ImuNoise.datasheet() if args.imu_noise == "datasheet" else ImuNoise()
    try:
        objects = _objects(args)
    except ValueError as err:
        return common.fail("render", err)
    margin = args.room_margin if args.room_margin is not None else (6.0 if objects.count else 3.0)
    if margin <= 0:
        return common.fail("render", "--room-margin must be > 0")
    config = RenderConfig(
        seed=args.seed, imu_noise=noise, objects=objects, scene=SceneConfig(margin_m=margin)
    )
    config = dataclasses.replace(
        config, sensor=dataclasses.replace(config.sensor, exposure_s=args.exposure_ms / 1000.0)
    )
    try:
        check_scheduler(args.scheduler)  # before the size is announced: a wrong value writes nothing
        n_frames, images, side = sequence_size(args.trajectory, args.timestamps, args.frames)
        detail = (
            f"{common.plural(n_frames, 'frame')} x ~{common.format_bytes(images / n_frames)} and "
            f"{common.format_bytes(side)} of IMU and ground truth"
        )
        stop = common.announce_size("render", args.output, images + side, detail, yes=args.yes)
        if stop is not None:
            return stop
        result = render_sequence(
            args.trajectory,
            args.timestamps,
            args.output,
            imu=args.imu,
            texture=args.texture,
            config=config,
            frames=args.frames,
            workers=args.workers,
            progress=not args.no_progress,
            force=args.force,
            scheduler=args.scheduler,
        )
    except (ValueError, FileNotFoundError, StaleOutputError) as err:
        return common.fail("render", err)
    m = result.manifest
    if result.status == "complete":
        print(f"{result.out}: already complete ({m['frames']} frames)")
        return 0
    rate = f", {m['frames_per_second']} frames/s" if m.get("frames_per_second") else ""
    if "masks" in m:
        share = m["masks"]
        rate += (
            f"; {len(m['objects'])} objects cover {100 * share['mask_share_mean']:.1f} % of the image on "
            f"average (95th percentile {100 * share['mask_share_p95']:.1f} %, max "
            f"{100 * share['mask_share_max']:.1f} %), masks in mav0/cam0/masks and {share['instances_txt']}"
        )
    print(
        f"{result.out}: {m['frames']} frames ({result.rendered} rendered now, {result.kept} kept) in "
        f"{result.seconds:.1f} s{rate}; texture: {m['texture']}; IMU: {m['imu']}"
    )
    return 0


def _objects(args: argparse.Namespace):
    """ObjectsConfig of --cars, --pedestrians and --parked."""
    from jsve.render import ObjectsConfig

    if args.cars < 0 or args.pedestrians < 0:
        raise ValueError("--cars and --pedestrians must be >= 0")
    parked = args.parked
    if parked != "all":
        if not parked.isdigit():
            raise ValueError(f"--parked must be a count or 'all', got {parked!r}")
        parked = int(parked)
    return ObjectsConfig(cars=args.cars, pedestrians=args.pedestrians, parked=parked)
