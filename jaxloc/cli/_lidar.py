"""``jaxloc localize-lidar``: M2Loc on an instance map and scan files or sequences."""

from __future__ import annotations

import argparse
import contextlib
import json
import time
import warnings
from pathlib import Path

import numpy as np

from jaxloc.cli._errors import InputError, note, reading
from jaxloc.cli._lidar_scans import (
    BAG_OPTIONS,
    POSES_OUT_HELP,
    add_drive_options,
    add_sequence_options,
    check_poses_out,
    drive_options,
    note_sequences,
)
from jaxloc.cli._options import RERUN_HELP, command, given, positive_float, positive_int

DESCRIPTION = """\
One-shot global localization of LiDAR scans in an instance map (M2Loc / TripletLoc).

MAP is an instance map folder (e.g. of build-lidar-map), or a map saved with --save-map (FILE.npz:
loaded, not described again; the settings but --scales and --tripletloc still apply):
  MAP/instances/15.txt, 17.txt, 18.txt   lines "id x y z" (trunks, poles, traffic signs)
  MAP/RSN/road_normal.txt                optional, lines "x y nx ny nz std_deg" (roll/pitch prior)
Each SCAN is one of:
  NAME.bin       a SemanticKITTI scan with NAME.label beside it or in ../labels/ (instances
                 clustered from the trunk, pole and traffic-sign points)
  SEQ/LiDAR/<sensor>/<stamp>.bin   a HeLiPR scan with SEQ/labels/<stamp>.label
  NAME.txt       instance centroids, lines "class_id x y z" (15, 17 or 18; '#' comments)
  a folder       instances/15.txt, 17.txt, 18.txt in the map's own format
  SEQ_DIR        a labelled sequence build-lidar-map reads: every --every-th scan, its poses the
                 ground truth unless --gt is given
  BAG            a ROS 1 .bag, ROS 2 bag folder or .mcap, alone: its labelled PointCloud2 clouds,
                 its odometry (used unless --odometry is given) and --gt-topic's ground truth
Per scan: T_map_scan (p_map = T_map_scan @ p_scan), valid or not, the clique size (--track: how
it was localized: tracked, relocalized, lost, or pending confirmation) and the times.
"""

EPILOG = f"""\
examples:
  jaxloc localize-lidar maps/KAIST04 \\
      scans/000000.bin
  jaxloc localize-lidar MAP scans/*.txt --gt poses.txt --json > result.json
  jaxloc localize-lidar MAP_DIR scans/*.bin --save-map map.npz   # describe once, save
  jaxloc localize-lidar map.npz KAIST05 --every 10 --poses-out kaist05.tum
  jaxloc localize-lidar map.npz drive.mcap --topic /points --accumulate 3 --poses-out est.mcap

--gt FILE: the ground-truth T_map_scan, a pose a line: KITTI 3x4 (12 numbers), 4x4 (16) or TUM
"t x y z qx qy qz qw" (t in seconds, or HeLiPR's integer nanoseconds), matched to timestamped
scans by time, else line i to the i-th scan. Then RTE (m), RRE (deg) and the success rate
(valid, RTE < 7.5 m, RRE < 10 deg) are printed.

{POSES_OUT_HELP}
"""


def add_parser(commands) -> None:
    """Register ``localize-lidar`` on the ``jaxloc`` subcommand parsers."""
    lidar = command(commands, "localize-lidar", DESCRIPTION, EPILOG)
    lidar.add_argument("map", type=Path, metavar="MAP", help="instance map folder or saved .npz")
    lidar.add_argument("scans", type=Path, nargs="+", metavar="SCAN", help="scan file(s)")
    lidar.add_argument("--gt", type=Path, help="ground-truth poses: KITTI, 4x4 or TUM (see below)")
    lidar.add_argument("--every", type=positive_int, default=1, help="of a sequence, every N-th")
    add_drive_options(lidar)
    lidar.add_argument("--save-map", type=Path, metavar="FILE", help="save the described map")
    lidar.add_argument("--json", action="store_true", help="print one JSON document instead")
    lidar.add_argument("--rerun", type=Path, metavar="F.rrd", help=RERUN_HELP)
    lidar.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_sequence_options(lidar)
    BAG_OPTIONS.add(lidar, "a bag SCAN (defaults: the bag's)")
    add_triplet_options(lidar)


def add_triplet_options(parser: argparse.ArgumentParser, scales: int | None = None) -> None:
    """The localization settings (:func:`triplet_config`); None defaults are the library's."""
    group = parser.add_argument_group("localization settings (defaults: m2loc_config's)")
    add = group.add_argument
    edges = "M2Loc descriptor scales: [0,20], (20,30], (30,40] m"
    add("--scales", type=int, choices=(1, 2, 3), default=scales, help=edges)
    add("--tripletloc", action="store_true", help="TripletLoc's descriptor (edge lengths)")
    add("-k", type=positive_int, help="map matches per scan instance and scale")
    add("--threshold", type=positive_float, help="consistency threshold of the match graph, m")
    add("--min-clique", type=positive_int, help="add scales while the clique is smaller (T)")
    add("--no-rsn", action="store_true", help="ignore the road-normal prior")
    published = "cliques may join associations of one vertex, no clique hypotheses"
    add("--no-robust", action="store_true", help=f"M2Loc as published (robust=False): {published}")


def _matching_options(args: argparse.Namespace) -> dict:
    """The options that do not change descriptors, as TripletConfig fields (given ones only)."""
    from jaxloc.m2loc._config import PUBLISHED_SETTINGS

    options = given(top_k=args.k, consistency_threshold=args.threshold, min_clique=args.min_clique)
    if args.no_rsn:
        options["use_rsn"] = False
    if args.no_robust:
        options.update(PUBLISHED_SETTINGS)
    return options


def triplet_config(args: argparse.Namespace):
    """The :class:`~jaxloc.m2loc.TripletConfig` of the localization options."""
    from jaxloc.m2loc import m2loc_config, tripletloc_config

    if args.tripletloc:
        return tripletloc_config(**_matching_options(args))
    scales = {} if args.scales is None else {"num_scales": args.scales}
    return m2loc_config(**scales, **_matching_options(args))


@contextlib.contextmanager
def notes_of_small_maps(command: str, name: str):
    """Each :class:`jaxloc.m2loc.SmallMapWarning` (a clamped ``top_k``) as a note on stderr."""
    from jaxloc.m2loc import SmallMapWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SmallMapWarning)
        yield
    for w in caught:
        if issubclass(w.category, SmallMapWarning):
            note(command, f"map {name}: {w.message}")
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def describe_map(points, labels, config, normals, name: str, command: str = "bench"):
    """:func:`jaxloc.m2loc.build_map` with its input errors as InputError and a clamped
    ``top_k`` as a note on stderr (``jaxloc COMMAND: note: ...``)."""
    from jaxloc.m2loc import build_map

    with reading(f"map {name}"), notes_of_small_maps(command, name):
        return build_map(points, labels, config, normals)


def _first_query_capacity(recording, config, args: argparse.Namespace) -> tuple[int, ...]:
    """:func:`jaxloc.m2loc._drive.first_query_capacity`; () for --accumulate and --track."""
    from jaxloc.m2loc._drive import first_query_capacity

    if recording is None or args.track or args.accumulate > 1:
        return ()
    return first_query_capacity(recording, config)


def open_map(path: Path, args: argparse.Namespace, recording=None):
    """(the described map of ``MAP``, seconds): :func:`jaxloc.io.open_triplet_map` of a saved
    ``.npz`` (the options that do not change descriptors override its settings) or of a map
    folder (described with the options while the first scan's query programs compile)."""
    from jaxloc.io import open_triplet_map

    start = time.perf_counter()
    if path.is_file() and (args.scales is not None or args.tripletloc):
        raise InputError(
            f"{path}: a saved map keeps the descriptors it was described with; drop "
            "--scales / --tripletloc (or describe the map folder again)"
        )
    with reading(), notes_of_small_maps(args.command, str(path)):
        if path.is_file():
            triplet_map = open_triplet_map(path, replace=_matching_options(args))
        else:
            config = triplet_config(args)
            capacities = _first_query_capacity(recording, config, args)
            triplet_map = open_triplet_map(path, config, query_capacities=capacities)
    return triplet_map, time.perf_counter() - start


def check_save_path(path: Path | None) -> None:
    """Before any work: a ``--save-map`` path must name an ``.npz`` file."""
    if path is not None and path.suffix != ".npz":
        raise InputError(f"--save-map {path}: the file name must end in .npz")


def check_localize_lidar(args: argparse.Namespace) -> None:
    """The options that depend on each other or on the file system, before any reading."""
    check_save_path(args.save_map)
    check_poses_out(args)
    drive_options(args)


def run_localize_lidar(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from jaxloc import io
    from jaxloc.m2loc import _evaluation as evaluation, localize_drive

    accumulate, drive_config = drive_options(args)  # checked by check_localize_lidar
    with reading():
        recording = io.open_lidar_recording(
            args.scans,
            layout=args.format,
            sensor=args.sensor,
            every=args.every,
            gt=args.gt,
            **BAG_OPTIONS.values(args),
        )
        drive = recording if args.odometry is None else recording.with_poses(args.odometry)
    odometry = given(odometry=recording.odometry if args.odometry is None else None)
    note_sequences(args, recording.sequences)
    triplet_map, build_s = open_map(args.map, args, recording)
    if args.save_map is not None:
        io.save_triplet_map(triplet_map, args.save_map)
    num_vertices = int(triplet_map.points.shape[0])
    say = (lambda _: None) if args.json else print
    say(
        f"map {args.map}: {num_vertices} instances, "
        f"{'with' if triplet_map.has_rsn else 'without'} road normals, "
        f"{'loaded' if args.map.is_file() else 'described'} in {build_s:.1f} s"
    )
    records = []
    bar = tqdm(total=len(recording), unit="scan", disable=len(recording) < 2 or args.no_progress)

    def progress(index: int, step) -> None:
        stamp, judged = recording.stamps[index], recording.has_pose[index]
        record = {"scan": recording.name(index)}
        record |= {} if stamp is None else {"timestamp_ns": int(stamp)}
        T_gt = recording.poses[index] if judged else None
        records.append(record | evaluation.step_record(step, T_gt, args.track))
        bar.update()
        if not args.json:
            tqdm.write(evaluation.format_record(records[-1]))

    with reading(), bar:
        result = localize_drive(
            triplet_map,
            drive,
            accumulate=accumulate,
            track=args.track,
            config=drive_config,
            progress=progress,
            **odometry,
        )
    if args.poses_out is not None:
        out = (args.poses_out, recording, result.poses, result.valid, args.pose_format)
        if left_out := io.write_lidar_poses(*out):
            note(
                args.command, f"{args.poses_out}: {left_out} scan(s) that did not localize left out"
            )
    if args.rerun is not None:
        seconds = None if recording.timestamps is None else recording.timestamps / 1e9
        drive_run = (args.rerun, triplet_map, result, recording.poses)
        io.write_drive_rerun(*drive_run, has_gt=recording.has_pose, timestamps=seconds)
        say(f"rerun: {args.rerun}")
    summary = {"map": str(args.map), "map_instances": num_vertices, "map_build_s": build_s}
    judged = np.asarray(recording.has_pose, bool)
    if judged.any():
        success = evaluation.localization_success(
            result.poses[judged], recording.poses[judged], result.valid[judged]
        )
        summary["success_rate"] = float(np.mean(success))
        rte, rre = evaluation.SUCCESS_RTE_M, evaluation.SUCCESS_RRE_DEG
        say(f"success (valid, RTE < {rte} m, RRE < {rre} deg): {success.sum()}/{len(success)}")
        if not judged.all():
            note(args.command, f"{int((~judged).sum())} scan(s) without ground truth")
    if args.json:
        print(json.dumps({"summary": summary, "scans": records}, indent=2))
    return 0
