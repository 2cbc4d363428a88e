"""``jaxloc localize-camera``: SG2Loc on a map file and a camera recording."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxloc.cli._errors import InputError, reading
from jaxloc.cli._options import (
    RERUN_HELP,
    OptionTable,
    add_list,
    command,
    given,
    nonnegative_float,
    positive_float,
    positive_int,
    seed,
)

DESCRIPTION = """\
Localize a camera recording in a scene graph (SG2Loc's coarse-to-fine particle filter).

MAP.npz is a map of `jaxloc build-scene-graph`. SEQ is one of (detected, or --format):
 scannet-export  a ScanNet export folder: color/N.jpg, depth/N.png (uint16 mm), pose/N.txt (4x4
                   camera-to-world; -inf: skipped), intrinsic/intrinsic_color.txt, _depth.txt
 sens            a ScanNet .sens file (frames numbered 0, 1, ...)
 3rscan          a 3RScan scan folder or its sequence/ (_info.txt, frame-NNNNNN.color.jpg,
                   .depth.pgm, .pose.txt); --rescan-json 3RScan.json (or --transform FILE)
                   puts a rescan's poses in its reference scan's frame
 rosbag          a ROS 1 .bag, ROS 2 bag folder or .mcap: colour, depth, CameraInfo, odometry
                   or /tf, label topics (each picked when it is the only one of its kind)
Patch embeddings of frame N: embeddings/N.npy ((rows, cols, d), d the map's), or label images
--labels DIR/N.png (class ids, 0 = unknown; --label-table maps raw ScanNet ids) made into
embeddings with the map's class embeddings. --odometry (default odometry.txt beside the frames:
lines "N m00 ... m33", camera-to-odometry, z up) gives the ego-motion and tilt.

Per frame: the estimate (x, y, z m, yaw deg, the map's frame), the verdict (act on the estimate
only when localized), its confidence (the probability of being within 0.5 m and 10 deg), with
--depth-check a depth-blind filter's verdict, and with ground truth the errors and recalls.
--online: what a live camera would have been told (jaxloc.sg2loc.online, one round at the first
stride). --poses-out: for evo.
"""

EPILOG = """\
examples:
  jaxloc localize-camera scene0000_00.npz scans/scene0000_00/export
  jaxloc localize-camera scene0000_00.npz scans/scene0000_00/scene0000_00.sens --step 10 \\
      --labels label-filt --label-table scannetv2-labels.combined.tsv --poses-out est.tum
  jaxloc localize-camera <ref_id>.npz 3RScan/<rescan_id> --rescan-json 3RScan.json
  jaxloc localize-camera room.npz seq --heights 1.2,1.3,1.4 --particles 4000 --plot run.png
  jaxloc localize-camera room.npz seq --max-frames 10 --refine --online --strides 10 --json
  jaxloc localize-camera office.npz office.mcap --label-topic /labels --gt gt.tum --rerun run.rrd
"""


#: A bag SEQ's topics (open_camera_recording's keywords): flag, metavar, help.
BAG_OPTIONS = OptionTable(
    (
        ("--image-topic", "TOPIC", "colour sensor_msgs/Image or CompressedImage"),
        ("--depth-topic", "TOPIC", "depth sensor_msgs/Image (16UC1 mm, 32FC1 m)"),
        ("--camera-info-topic", "TOPIC", "colour CameraInfo (default: the images' camera_info)"),
        ("--depth-info-topic", "TOPIC", "depth CameraInfo (default: the depth's camera_info)"),
        ("--odometry-topic", "TOPIC", "pose topic, /tf or none (default: sole Odometry, else /tf)"),
        ("--odometry-frame", "FRAME", "/tf odometry's fixed frame (default odom, else the root)"),
        ("--label-topic", "TOPIC", "label images (class ids), made into patch embeddings"),
        ("--gt-topic", "TOPIC", "ground truth: a nav_msgs/Odometry or PoseStamped topic"),
        ("--gt", "FILE", "ground truth: a pose file (TUM lines interpolated to the frames)"),
    )
)


def add_parser(commands) -> None:
    """Register ``localize-camera`` on the ``jaxloc`` subcommand parsers."""
    parser = command(commands, "localize-camera", DESCRIPTION, EPILOG)
    parser.add_argument("map", type=Path, metavar="MAP.npz", help="the map file")
    parser.add_argument("seq_dir", type=Path, metavar="SEQ", help="the recording (see above)")
    group = parser.add_argument_group("the recording (defaults: open_camera_recording's)")
    add = group.add_argument
    add("--format", choices=("scannet-export", "sens", "3rscan", "rosbag"), help="its layout")
    for name, metavar, text in (
        ("--embeddings", "DIR", "patch embeddings N.npy"),
        ("--labels", "DIR", "label images N.png"),
        ("--label-table", "TSV", "raw id -> class id table"),
        ("--rescan-json", "JSON", "3RScan.json (3rscan)"),
        ("--transform", "FILE", "4x4 applied to the poses"),
        ("--odometry", "FILE", "'N m00 ... m33', TUM or KITTI poses"),
    ):
        add(name, type=Path, metavar=metavar, help=text)
    add("--label-column", help="--label-table's class column (default nyu40id)")
    add("--scan-id", help="the rescan's id in --rescan-json (default: the folder's name)")
    grid = "ROWS COLS of the patch grid of embeddings made from label images"
    add_list(add, "--patches", positive_int, "9,16", grid, count=2, metavar="N")
    add("--width", type=positive_int, default=320, help="working width, px")
    add("--height", type=positive_int, help="working height, px (default: keep the aspect)")
    add("--step", type=positive_int, help="use every STEP-th frame")
    add("--max-frames", type=positive_int, help="use at most this many frames")
    add("--no-depth", action="store_true", help="ignore depth/")
    add("--no-rgb", action="store_true", help="no colour score")
    BAG_OPTIONS.add(parser, "a bag SEQ (defaults: the bag's)")
    add = parser.add_argument_group("filter settings (defaults: SG2LocConfig's)").add_argument
    add("--particles", type=positive_int, help="particle capacity")
    strides = "ray stride per round (with --online: the first)"
    add_list(add, "--strides", positive_int, "20,8,4", strides, metavar="S")
    add_list(add, "--boxes", positive_float, "0.8,0.4", "re-init box half-widths, m", metavar="M")
    heights = "initial camera heights above the floor, m (default PAPER_HEIGHTS)"
    add_list(add, "--heights", nonnegative_float, "1.2,1.3,1.4", heights, metavar="H")
    add("--online", action="store_true", help="stream the frames (jaxloc.sg2loc.online)")
    check = "check the estimates with a depth-blind filter (depth_blind_check; not --online)"
    add("--depth-check", action="store_true", help=check)
    add("--seed", type=seed, default=0, help="random seed")
    add = parser.add_argument_group("output").add_argument
    add("--json", action="store_true", help="print one JSON document instead")
    add("--poses-out", type=Path, metavar="FILE", help="estimated poses, for evo")
    add("--pose-format", choices=("tum", "kitti"), default="tum", help="--poses-out's format")
    add("--refine", action="store_true", help="refine the last frame with depth")
    add("--plot", type=Path, metavar="FILE", help="figure of particles (PNG)")
    add("--rerun", type=Path, metavar="F.rrd", help=RERUN_HELP)
    add("--no-progress", action="store_true", help="no progress bar")


def _config(args: argparse.Namespace):
    """The :class:`~jaxloc.sg2loc.SG2LocConfig` of the options given, its defaults else (with
    ``--online`` the stream runs its first stride)."""
    from jaxloc.sg2loc import SG2LocConfig, kld_for_capacity

    capacity = args.particles or SG2LocConfig.capacity
    options = given(strides=args.strides, box_half_widths=args.boxes, heights=args.heights)
    with reading():
        return SG2LocConfig(**options, capacity=capacity, kld=kld_for_capacity(capacity))


def _load_recording(args: argparse.Namespace):
    """:func:`jaxloc.io.open_camera_recording` with the options given, its defaults else."""
    from jaxloc.io import open_camera_recording

    renamed = {"embeddings_dir": "embeddings", "labels_dir": "labels", "patch_shape": "patches"}
    same = ("format", "width", "height", "label_table", "label_column", "rescan_json", "scan_id")
    names = (*same, "transform", "odometry", "step", "max_frames", *renamed)
    options = given(**{name: getattr(args, renamed.get(name, name)) for name in names})
    options |= BAG_OPTIONS.values(args)
    with reading():
        return open_camera_recording(
            args.seq_dir,
            map_file=args.map,
            use_depth=not args.no_depth,
            use_rgb=not args.no_rgb,
            **options,
        )


def run_localize_camera(args: argparse.Namespace) -> int:
    import jax
    from tqdm.auto import tqdm

    from jaxloc.io import write_camera_poses, write_rerun
    from jaxloc.io.camera_recording import camera_pose_matrices
    from jaxloc.io.scene_map import load_scene
    from jaxloc.metrics import summarize_sequence
    from jaxloc.sg2loc import check_ssim_strides, depth_blind_check, localize, online, warm_up
    from jaxloc.sg2loc._report import format_report, refinement_record, run_record
    from jaxloc.sg2loc.figures import plot_rounds

    if args.online and (args.plot is not None or args.depth_check):
        flag = "--plot draws" if args.plot is not None else "--depth-check checks"
        raise InputError(f"{flag} the coarse-to-fine rounds; there are none with --online")
    config = _config(args)
    with reading():
        scene = load_scene(args.map)
    folder = _load_recording(args)
    seq = folder.sequence
    if (args.refine or args.depth_check) and seq.depth is None:
        flag = "--refine" if args.refine else "--depth-check"
        raise InputError(f"{flag} needs depth images in {args.seq_dir} (and no --no-depth)")
    if seq.rgb is not None:
        strides = config.strides[:1] if args.online else config.strides
        width, height = seq.camera.width, seq.camera.height
        with reading():
            check_ssim_strides(strides, width, height, "--strides", "a larger --width, or --no-rgb")
    if not args.json:
        print(
            f"map: {scene.num_objects} objects, {scene.num_triangles} triangles; sequence: "
            f"{seq.num_frames} frames of a {folder.format} recording ({len(folder.skipped)} "
            f"skipped without a pose), {seq.camera.width}x{seq.camera.height} px, "
            f"{seq.patch_shape[0]}x{seq.patch_shape[1]} patches, depth "
            f"{'yes' if seq.depth is not None else 'no'}"
        )
    key, progress = jax.random.key(args.seed), not args.no_progress
    if args.online:
        with tqdm(total=seq.num_frames, unit="frame", disable=not progress) as bar:
            result = online.filter_sequence(
                key, scene, seq, config, progress=lambda t: bar.update()
            )
    else:  # the rounds compile side by side (warm_up's threads); localize waits for them
        warm_up(key, scene, seq, config, progress=progress)
        result = localize(key, scene, seq, config, progress=progress)
    report = run_record(result, folder, args.map, args.seq_dir, args.online)
    poses = np.asarray(report["poses"])
    if args.depth_check:
        report["depth_check"] = depth_blind_check(key, scene, seq, config).passed.tolist()
    if folder.poses_gt is not None:
        report.update(summarize_sequence(poses, folder.poses_gt))
    if args.refine:
        truth = folder.poses_gt is not None
        T_gt = camera_pose_matrices(folder.poses_gt[-1:], folder.tilt_gt[-1:])[0] if truth else None
        report["refined"] = refinement_record(scene, seq, poses[-1], T_gt)
    if args.poses_out is not None:
        write_camera_poses(args.poses_out, folder, poses, args.pose_format)
        report["poses_out"] = str(args.poses_out)
    if args.plot is not None:
        report["figure"] = str(plot_rounds(result, folder.poses_gt, args.plot, scene=scene))
    if args.rerun is not None:
        report["rerun"] = str(write_rerun(args.rerun, scene, result, folder, folder.poses_gt))
    print(json.dumps(report) if args.json else format_report(report))
    return 0
