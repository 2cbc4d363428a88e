"""``jaxloc localize-camera``: SG2Loc on a map file and a camera recording (ScanNet export folder,
ScanNet ``.sens`` or 3RScan sequence)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxloc.cli._demo import ray_grid_shape
from jaxloc.cli._errors import InputError
from jaxloc.cli._options import nonnegative_float, positive_float, positive_int, seed

DESCRIPTION = """\
Localize a camera sequence in a scene graph (SG2Loc's coarse-to-fine particle filter).

MAP.npz is a map written by `jaxloc build-scene-graph` (or jaxloc.save_scene). SEQ is one of
(detected; --format names one):
 scannet-export  a ScanNet export folder (SensReader's layout):
                   color/N.jpg, depth/N.png (uint16 mm), pose/N.txt (4x4 camera-to-world; -inf =
                   no pose, skipped), intrinsic/intrinsic_color.txt, intrinsic_depth.txt
 sens            a ScanNet .sens file, read frame by frame (frames numbered 0, 1, ...)
 3rscan          a 3RScan scan folder <scan_id>/ or its sequence/: _info.txt,
                   frame-NNNNNN.color.jpg, .depth.pgm, .pose.txt (images used as stored); a
                   rescan's poses go to its reference scan's frame with --rescan-json 3RScan.json
                   (or --transform FILE, a 4x4 rescan-to-reference matrix)
Patch embeddings per frame number N: embeddings/N.npy ((rows, cols, d), d = the map's dimension;
--embeddings DIR, default embeddings/ beside the frames) or, without them, label images
--labels DIR/N.png (8- or 16-bit class ids, 0 = unknown; --label-table maps raw ScanNet ids, as in
label-filt/, to the map's classes), turned into embeddings with the map's class embeddings.
An odometry file (--odometry, default odometry.txt beside the frames: lines "N m00 ... m33",
camera-to-odometry, z up) gives the ego-motion and tilt instead of the recording's poses.

Per frame it prints the estimate (x, y, z in metres, yaw in degrees; the map's frame), the verdict
(localized or not: act on the estimate only when localized; jaxloc.sg2loc._verdict) and, with
ground-truth poses, the position and rotation errors and the recalls. --online feeds the frames
one at a time to the streaming filter (jaxloc.sg2loc.online: one round at the first stride,
what a live camera would have been told) instead of the coarse-to-fine rounds over the sequence.
--poses-out writes the estimated camera-to-world poses for evo (TUM: the frame's timestamp in
seconds from a .sens, else its number; KITTI: one 3x4 per line).
"""

EPILOG = """\
examples:
  jaxloc localize-camera scene0000_00.npz scans/scene0000_00/export
  jaxloc localize-camera scene0000_00.npz scans/scene0000_00/scene0000_00.sens --step 10 \
      --labels label-filt --label-table scannetv2-labels.combined.tsv --poses-out est.tum
  jaxloc localize-camera <ref_id>.npz 3RScan/<rescan_id> --rescan-json 3RScan.json
  jaxloc localize-camera room.npz seq --heights 1.2 1.3 1.4 1.5 --particles 4000 --plot run.png
  jaxloc localize-camera room.npz seq --max-frames 10 --step 5 --refine --json > result.json
  jaxloc localize-camera room.npz seq --online --strides 20

exit status: 0 on success, 2 on missing or malformed files or bad options (one-line message).
"""


def add_parser(commands) -> None:
    """Register ``localize-camera`` on the ``jaxloc`` subcommand parsers."""
    parser = commands.add_parser(
        "localize-camera",
        help="localize a folder of RGB-D frames in a scene graph (SG2Loc)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("map", type=Path, metavar="MAP.npz", help="the map file")
    parser.add_argument("seq_dir", type=Path, metavar="SEQ", help="the recording (see above)")
    data = parser.add_argument_group("the recording")
    data.add_argument("--format", choices=("scannet-export", "sens", "3rscan"), help="its layout")
    data.add_argument("--embeddings", type=Path, metavar="DIR", help="patch embeddings N.npy")
    data.add_argument("--labels", type=Path, metavar="DIR", help="label images N.png")
    data.add_argument("--label-table", type=Path, metavar="TSV", help="raw id -> class id table")
    data.add_argument(
        "--label-column", default="nyu40id", help="--label-table's class column (default nyu40id)"
    )
    data.add_argument(
        "--patches", type=positive_int, nargs=2, default=[9, 16], metavar=("ROWS", "COLS"),
        help="patch grid of embeddings made from label images (default 9 16)",
    )  # fmt: skip
    data.add_argument("--rescan-json", type=Path, metavar="JSON", help="3RScan.json (3rscan)")
    data.add_argument("--scan-id", help="the rescan's id in --rescan-json (default: folder name)")
    data.add_argument("--transform", type=Path, metavar="FILE", help="4x4 applied to the poses")
    data.add_argument(
        "--odometry", type=Path, metavar="FILE", help="'N m00 ... m33', TUM or KITTI poses"
    )
    group = parser.add_argument_group("filter settings")
    group.add_argument("--particles", type=positive_int, default=2500, help="particle capacity")
    group.add_argument(
        "--strides",
        type=positive_int,
        nargs="+",
        default=[20, 8, 4],
        help="ray stride per round (with --online: the first)",
    )
    group.add_argument(
        "--boxes",
        type=positive_float,
        nargs="+",
        default=[0.8, 0.4],
        help="re-init box half-widths (m)",
    )
    group.add_argument(
        "--online",
        action="store_true",
        help="stream the frames one at a time (jaxloc.sg2loc.online) instead of the rounds",
    )
    group.add_argument(
        "--heights",
        type=nonnegative_float,
        nargs="+",
        help="initial camera heights above the floor, m (default the paper's, "
        "jaxloc.sg2loc._particles.PAPER_HEIGHTS)",
    )
    group.add_argument(
        "--width", type=positive_int, default=320, help="working width, px (default 320)"
    )
    group.add_argument(
        "--height", type=positive_int, help="working height, px (default: keep the aspect)"
    )
    group.add_argument("--step", type=positive_int, default=1, help="use every STEP-th frame")
    group.add_argument("--max-frames", type=positive_int, help="use at most this many frames")
    group.add_argument("--no-depth", action="store_true", help="ignore depth/")
    group.add_argument("--no-rgb", action="store_true", help="no colour score")
    group.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    out = parser.add_argument_group("output")
    out.add_argument("--json", action="store_true", help="print one JSON document instead")
    out.add_argument("--poses-out", type=Path, metavar="FILE", help="estimated poses, for evo")
    out.add_argument(
        "--pose-format", choices=("tum", "kitti"), default="tum", help="--poses-out's format"
    )
    out.add_argument("--refine", action="store_true", help="refine the last frame with depth")
    out.add_argument("--plot", type=Path, metavar="FILE", help="figure of particles (PNG)")
    out.add_argument("--no-progress", action="store_true", help="no progress bar")


def _config(args: argparse.Namespace):
    """The :class:`~jaxloc.sg2loc.SG2LocConfig` of the options (offline, or with ``--online``
    the streaming filter's: its first stride)."""
    from jaxloc.sg2loc import PAPER_HEIGHTS, KLDConfig, SG2LocConfig

    heights = tuple(PAPER_HEIGHTS if args.heights is None else args.heights)
    kld = KLDConfig(min_particles=min(500, args.particles), max_particles=args.particles)
    try:
        return SG2LocConfig(
            capacity=args.particles,
            strides=tuple(args.strides),
            box_half_widths=tuple(args.boxes),
            heights=heights,
            kld=kld,
        )
    except ValueError as error:
        raise InputError(str(error)) from None


def _refine_last(scene, folder, last_pose) -> dict:
    from jaxloc.io.camera_recording import camera_pose_matrices
    from jaxloc.metrics import position_error, rotation_error_deg
    from jaxloc.sg2loc.refine import refine

    refined = refine(scene, folder.sequence, last_pose)
    T = np.asarray(refined.pose.as_matrix(), np.float64)
    out = {"ok": bool(refined.ok), "status": int(refined.status), "T_world_cam": T.tolist()}
    if folder.poses_gt is not None:
        T_gt = camera_pose_matrices(folder.poses_gt[-1:], folder.tilt_gt[-1:])[0]
        out["position_error_m"] = float(position_error(T[:3, 3], T_gt[:3, 3]))
        out["rotation_error_deg"] = float(rotation_error_deg(T[:3, :3], T_gt[:3, :3]))
    return out


def _load_recording(args: argparse.Namespace):
    """The recording of ``args.seq_dir`` as a query for ``args.map``
    (:func:`jaxloc.io.open_camera_recording`)."""
    from jaxloc.io import open_camera_recording

    return open_camera_recording(
        args.seq_dir,
        format=args.format,
        map_file=args.map,
        width=args.width,
        height=args.height,
        embeddings_dir=args.embeddings,
        labels_dir=args.labels,
        label_table=args.label_table,
        label_column=args.label_column,
        patch_shape=tuple(args.patches),
        rescan_json=args.rescan_json,
        scan_id=args.scan_id,
        transform=args.transform,
        odometry=args.odometry,
        step=args.step,
        max_frames=args.max_frames,
        use_depth=not args.no_depth,
        use_rgb=not args.no_rgb,
    )


def _localize(key, scene, seq, config, args):
    """The coarse-to-fine rounds (:func:`~jaxloc.sg2loc.localize`) or, with ``--online``, the
    stream (:func:`~jaxloc.sg2loc.online.filter_sequence`) of the sequence."""
    from tqdm.auto import tqdm

    from jaxloc.sg2loc import localize, online, warm_up

    if not args.online:
        # the rounds' programs compile side by side (warm_up's threads); localize waits for them
        warm_up(key, scene, seq, config, progress=not args.no_progress)
        return localize(key, scene, seq, config, progress=not args.no_progress)
    with tqdm(total=seq.num_frames, unit="frame", disable=args.no_progress) as bar:
        return online.filter_sequence(key, scene, seq, config, progress=lambda t: bar.update(1))


def run_localize_camera(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.io import write_camera_poses
    from jaxloc.io.scene_map import load_scene
    from jaxloc.metrics import summarize, yaw_pose_errors
    from jaxloc.sg2loc._scores import SSIM_WINDOW
    from jaxloc.sg2loc.figures import plot_rounds

    if args.online and args.plot is not None:
        raise InputError("--plot draws the coarse-to-fine rounds; there are none with --online")
    config = _config(args)
    try:
        scene = load_scene(args.map)
        folder = _load_recording(args)
    except ValueError as error:
        raise InputError(str(error)) from None
    seq = folder.sequence
    if args.refine and seq.depth is None:
        raise InputError(f"--refine needs depth images in {args.seq_dir} (and no --no-depth)")
    if seq.rgb is not None:
        for stride in args.strides[:1] if args.online else args.strides:
            rows, cols = ray_grid_shape(stride, seq.camera.width, seq.camera.height)
            if min(rows, cols) < SSIM_WINDOW:
                raise InputError(
                    f"--strides: stride {stride} casts {cols}x{rows} rays at {seq.camera.width}x"
                    f"{seq.camera.height} px; the colour score (SSIM) needs {SSIM_WINDOW}x"
                    f"{SSIM_WINDOW}: use smaller --strides, a larger --width, or --no-rgb"
                )
    if not args.json:
        print(
            f"map: {scene.num_objects} objects, {scene.num_triangles} triangles; sequence: "
            f"{seq.num_frames} frames of a {folder.format} recording ({len(folder.skipped)} "
            "skipped without a pose), "
            f"{seq.camera.width}x{seq.camera.height} px, {seq.patch_shape[0]}x"
            f"{seq.patch_shape[1]} patches, depth {'yes' if seq.depth is not None else 'no'}"
        )
    result = _localize(jax.random.key(args.seed), scene, seq, config, args)
    poses = np.asarray(result.pose if args.online else result.poses, np.float64)
    localized = np.asarray(result.localized, bool)
    report: dict = {
        "map": str(args.map),
        "sequence": str(args.seq_dir),
        "format": folder.format,
        "frames": list(folder.frame_ids),
        "skipped": list(folder.skipped),
        "mode": "online" if args.online else "offline",
        "poses": poses.tolist(),
        "localized": localized.tolist(),
    }
    errors = None
    if folder.poses_gt is not None:
        errors = yaw_pose_errors(poses, folder.poses_gt)
        report["position_error_m"] = errors[0].tolist()
        report["rotation_error_deg"] = errors[1].tolist()
        report["all_frames"] = summarize(*errors)
        report["last_frame"] = summarize(errors[0][-1:], errors[1][-1:])
    if args.refine:
        report["refined"] = _refine_last(scene, folder, poses[-1])
    if args.poses_out is not None:
        write_camera_poses(args.poses_out, folder, poses, args.pose_format)
        report["poses_out"] = str(args.poses_out)
    if args.plot is not None:
        report["figure"] = str(plot_rounds(result, folder.poses_gt, args.plot, scene=scene))
    if args.json:
        print(json.dumps(report))
        return 0
    for t, number in enumerate(folder.frame_ids):
        x, y, z, yaw = poses[t]
        verdict = "localized" if localized[t] else "NOT localized"
        line = (
            f"frame {number}: {verdict}, x {x:.3f} y {y:.3f} z {z:.3f} m, "
            f"yaw {np.degrees(yaw):.1f} deg"
        )
        if errors is not None:
            line += f" | error {errors[0][t]:.3f} m, {errors[1][t]:.2f} deg"
        print(line)
    print(f"localized: {int(localized.sum())} of {len(localized)} frames")
    for name in ("all_frames", "last_frame"):
        if name in report:
            values = ", ".join(f"{k} {v:.3f}" for k, v in report[name].items())
            print(f"{name.replace('_', ' ')}: {values}")
    if "refined" in report:
        refined = report["refined"]
        line = f"refined last frame: ok {refined['ok']} (status {refined['status']})"
        if "position_error_m" in refined:
            line += (
                f", error {refined['position_error_m']:.3f} m, "
                f"{refined['rotation_error_deg']:.2f} deg"
            )
        print(line)
        print("T_world_cam =\n" + np.array2string(np.asarray(refined["T_world_cam"]), precision=4))
    if "figure" in report:
        print(f"figure: {report['figure']}")
    return 0
