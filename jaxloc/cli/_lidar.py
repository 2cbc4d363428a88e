"""``jaxloc localize-lidar``: M2Loc on a HeLiPR/TripletLoc instance map and scan files or
sequences (SemanticKITTI, plain or HeLiPR layout)."""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from jaxloc.cli._errors import InputError
from jaxloc.cli._lidar_scans import (
    POSES_OUT_HELP,
    check_poses_out,
    drive_options,
    note,
    note_sequences,
    reading,
)

DESCRIPTION = """\
One-shot global localization of LiDAR scans in an instance map (M2Loc / TripletLoc).

MAP is a HeLiPR/TripletLoc instance map folder (e.g. written by build-lidar-map):
  MAP/instances/15.txt, 17.txt, 18.txt   lines "id x y z" (trunks, poles, traffic signs; map
                                         frame, metres)
  MAP/RSN/road_normal.txt                optional, lines "x y nx ny nz std_deg": road-surface
                                         normals, used as a roll/pitch prior
or a described map saved with --save-map (FILE.npz): it loads in about a second instead of being
described again; -k, --threshold, --min-clique and --no-rsn still apply to it. A map smaller than
-k (default 25) is used with -k clamped to its vertex count (a note on stderr).

Each SCAN is one of:
  NAME.bin       a SemanticKITTI scan (float32 x y z intensity); its labels NAME.label are read
                 from beside it or from ../labels/ (the dataset layout). Instances are clustered
                 from the trunk, pole and traffic-sign points (TripletLoc's recipe).
  SEQ/LiDAR/<sensor>/<stamp>.bin
                 a HeLiPR scan (the sensor's point records) with SEQ/labels/<stamp>.label
  NAME.txt       instance centroids already extracted: lines "class_id x y z" (class_id 15, 17
                 or 18; scan frame, metres; '#' starts a comment)
  a folder       instances/15.txt, 17.txt, 18.txt in the map's own format
  SEQ_DIR        a labelled sequence in any layout build-lidar-map reads (SemanticKITTI,
                 plain with velodyne/, HeLiPR / TripletLoc; --format, --sensor): every
                 --every-th scan of it; its poses (poses.txt with calib.txt, or HeLiPR's
                 LiDAR_GT/<Sensor>_gt.txt) give the ground truth when --gt is not given

With --track (odometry from --odometry or the sequence's poses), a scan after a verified pose is
localized near the predicted pose in milliseconds (global localization when that fails); each
record says "tracked", "relocalized", "lost" or "pending" (a global pose waiting for the next
scan's to confirm it: not reported as valid).

The map's descriptors are built once; every scan is then described, matched, and registered.
Per scan it prints the 4x4 T_map_scan (p_map = T_map_scan @ p_scan), whether it is valid, the
size of the maximum clique of consistent matches, and the times. The first scan of each
instance count band (32, 64, ...) also compiles (reported separately).
"""

EPILOG = f"""\
examples:
  jaxloc localize-lidar ../shared/data/helipr_instance_maps/KAIST04 \\
      ../shared/data/semantickitti_scan/000000.bin
  jaxloc localize-lidar MAP scan_centroids.txt --scales 1 -k 10
  jaxloc localize-lidar MAP scans/*.txt --gt poses.txt --json > result.json
  jaxloc localize-lidar MAP_DIR scans/*.bin --save-map map.npz   # describe once, save
  jaxloc localize-lidar map.npz sequences/00 --every 20           # reuse the saved map
  jaxloc localize-lidar maps/KAIST04 KAIST05 --every 10 --poses-out kaist05.tum
  evo_ape tum gt_in_seconds.tum kaist05.tum                       # no alignment: RTE

--gt FILE: the ground-truth T_map_scan, one pose a line: 12 numbers (KITTI 3x4, row-major), 16
(4x4, row-major) or 8 (TUM "t x y z qx qy qz qw", t in seconds; or HeLiPR's LiDAR_GT lines,
t in integer nanoseconds). Poses with timestamps are matched to scans with timestamps (HeLiPR
scans, sequences with times.txt) by time: integer nanoseconds exactly, seconds within 1 ms; a
scan without a pose at its time is not judged. Otherwise line i belongs to the i-th scan. Then
RTE (m) and RRE (deg) are printed, and the success rate (valid, RTE < 7.5 m, RRE < 10 deg).

{POSES_OUT_HELP}

exit status: 0 on success, 2 on missing or malformed files or bad options (one-line message).
"""


#: Defaults of the localization options (None in argparse, so that a saved map can tell which
#: options were given).
DEFAULT_SCALES, DEFAULT_K, DEFAULT_THRESHOLD, DEFAULT_MIN_CLIQUE = 3, 25, 1.0, 10


def _matching_options(args: argparse.Namespace) -> dict:
    """The options that do not change descriptors, as TripletConfig fields (given ones only)."""
    given = {
        "top_k": args.k,
        "consistency_threshold": args.threshold,
        "min_clique": args.min_clique,
    }
    options = {name: value for name, value in given.items() if value is not None}
    if args.no_rsn:
        options["use_rsn"] = False
    if args.no_robust:
        options.update(one_to_one=False, registration_attempts=1, hypotheses=0)
    return options


def triplet_config(args: argparse.Namespace):
    from jaxloc.m2loc import m2loc_config, tripletloc_config

    options = dict(
        top_k=DEFAULT_K,
        consistency_threshold=DEFAULT_THRESHOLD,
        min_clique=DEFAULT_MIN_CLIQUE,
    )
    options.update(_matching_options(args))
    if args.tripletloc:
        return tripletloc_config(**options)
    return m2loc_config(args.scales or DEFAULT_SCALES, **options)


def notes_of_small_maps(command: str, name: str):
    """A context manager that turns :class:`jaxloc.m2loc.SmallMapWarning` into one note per
    warning on stderr (a clamped ``top_k`` is not an error)."""
    import contextlib

    from jaxloc.m2loc import SmallMapWarning

    @contextlib.contextmanager
    def catching():
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", SmallMapWarning)
            yield
        for warning in caught:
            if issubclass(warning.category, SmallMapWarning):
                note(command, f"map {name}: {warning.message}")
            else:
                warnings.warn_explicit(
                    warning.message, warning.category, warning.filename, warning.lineno
                )

    return catching()


def describe_map(
    points: np.ndarray, labels: np.ndarray, config, normals, name: str, command: str = "bench"
):
    """:func:`jaxloc.m2loc.build_map` with its input errors reported as InputError and a clamped
    ``top_k`` as a note on stderr (``jaxloc COMMAND: note: ...``)."""
    from jaxloc.m2loc import build_map

    try:
        with notes_of_small_maps(command, name):
            return build_map(points, labels, config, normals)
    except ValueError as error:
        raise InputError(f"map {name}: {error}") from error


def _first_query_capacity(recording, config, args: argparse.Namespace) -> tuple[int, ...]:
    """The padded size of the first scan's query, for its programs to compile while the map is
    described; () for a drive that runs other programs (--accumulate, --track), a scan too small
    to localize, or one that does not read or that localize_scan refuses (its error comes when
    it is localized, and nothing was compiled for it)."""
    from jaxloc.m2loc import pad_scan

    if recording is None or not len(recording) or args.track or args.accumulate > 1:
        return ()
    try:
        scan = recording.instances(0, config.descriptor.classes)
        padded = pad_scan(scan.points, scan.labels, config)
    except (OSError, ValueError):
        return ()
    return (padded.points.shape[0],) if len(scan.points) >= 3 else ()


def open_map(path: Path, args: argparse.Namespace, recording=None):
    """The described map of ``MAP`` (:func:`jaxloc.io.open_triplet_map`): a saved ``.npz`` (the
    options that do not change descriptors override its settings) or a map folder (described with
    the options, while the query programs of ``recording``'s first scan compile). Returns the
    TripletMap and the number of seconds it took."""
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
    """The options of ``localize-lidar`` that depend on each other or on the file system, before
    the map or any scan is read (the values themselves are checked where they are parsed)."""
    check_save_path(args.save_map)
    check_poses_out(args)
    drive_options(args)


def _scan_record(recording, index: int, step, track: bool) -> dict:
    """The JSON record of scan ``index`` (a ``DriveStep``)."""
    from jaxloc.m2loc import TrackStatus, localization_errors

    scan, result = step.instances, step.result
    counts = {int(c): int(np.sum(scan.labels == c)) for c in np.unique(scan.labels)}
    record = {
        "scan": recording.name(index),
        "instances": int(len(scan.points)),
        "instances_per_class": {str(c): n for c, n in counts.items()},
        "valid": bool(result.valid),
        "ambiguous": bool(result.ambiguous),
        "clique_size": int(result.clique_size),
        "scales_used": int(result.scales_used),
        "T_map_scan": np.round(result.pose, 6).tolist(),
        "load_ms": round(step.load_ms, 3),
        "descriptor_ms": round(result.descriptor_time_ms, 3),
        "match_ms": round(result.match_time_ms, 3),
        "compile_s": round(step.compile_s, 3),
    }
    if recording.stamps[index] is not None:
        record["timestamp_ns"] = int(recording.stamps[index])
    if recording.has_pose[index]:
        rte, rre = localization_errors(result.pose, recording.poses[index])
        record["rte_m"], record["rre_deg"] = float(rte), float(rre)
    if track:
        record["track"] = TrackStatus(step.status).name.lower()
    if step.fused is not None:
        record["fused_scans"] = int(step.fused.members.shape[1])
        record["fused_instances"] = len(step.fused.points)
        if not track:
            record["small_clique"] = step.small_clique
    return record


def _why_not_valid(record: dict) -> str:
    """Why a pose that passed the clique and verification tests was refused ("" otherwise)."""
    from jaxloc.m2loc._accumulation import WINDOW_MIN_CLIQUE

    if record["ambiguous"]:
        return " (ambiguous: another place fits as well)"
    if record.get("small_clique"):
        return f" (a window's pose needs a clique of {WINDOW_MIN_CLIQUE})"
    return ""


def _format_record(record: dict) -> str:
    classes = ", ".join(f"{n} x {c}" for c, n in record["instances_per_class"].items())
    how = f"clique {record['clique_size']}, scales used {record['scales_used']}"
    if "track" in record:
        how = f"{record['track']}, {record['clique_size']} local associations"
    lines = [
        f"{record['scan']}: {record['instances']} instances ({classes or 'none'}); "
        f"{'valid' if record['valid'] else 'NOT valid'}{_why_not_valid(record)}, {how}",
        "  T_map_scan =",
    ]
    lines += ["    " + " ".join(f"{v:12.4f}" for v in row) for row in record["T_map_scan"]]
    timing = (
        f"  time: load {record['load_ms']:.1f} ms, descriptors {record['descriptor_ms']:.1f} ms, "
        f"match + clique + pose {record['match_ms']:.1f} ms"
    )
    if "track" in record:
        timing = f"  time: load {record['load_ms']:.1f} ms, step {record['match_ms']:.1f} ms"
    if record["compile_s"]:
        timing += f" (first scan of this size: +{record['compile_s']:.1f} s compile or load)"
    lines.append(timing)
    if "rte_m" in record:
        lines.append(f"  RTE {record['rte_m']:.3f} m, RRE {record['rre_deg']:.3f} deg")
    return "\n".join(lines)


def run_localize_lidar(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from jaxloc.io import open_lidar_recording, save_triplet_map, write_lidar_poses
    from jaxloc.m2loc import localize_drive
    from jaxloc.m2loc._evaluation import SUCCESS_RRE_DEG, SUCCESS_RTE_M

    accumulate, drive_config = drive_options(args)  # checked by check_localize_lidar
    with reading():
        recording = open_lidar_recording(
            args.scans, layout=args.format, sensor=args.sensor, every=args.every, gt=args.gt
        )
        drive = recording if args.odometry is None else recording.with_poses(args.odometry)
    note_sequences(args, recording.sequences)
    triplet_map, build_s = open_map(args.map, args, recording)
    if args.save_map is not None:
        save_triplet_map(triplet_map, args.save_map)
    num_vertices, has_rsn = int(triplet_map.points.shape[0]), triplet_map.has_rsn
    say = (lambda _: None) if args.json else print
    say(
        f"map {args.map}: {num_vertices} instances, "
        f"{'with' if has_rsn else 'without'} road normals, "
        f"{'loaded' if args.map.is_file() else 'described'} in {build_s:.1f} s"
    )
    records = []
    bar = tqdm(total=len(recording), unit="scan", disable=len(recording) < 2 or args.no_progress)

    def progress(index: int, step) -> None:
        records.append(_scan_record(recording, index, step, args.track))
        bar.update()
        if not args.json:
            tqdm.write(_format_record(records[-1]))

    with reading(), bar:
        result = localize_drive(
            triplet_map,
            drive,
            accumulate=accumulate,
            track=args.track,
            config=drive_config,
            progress=progress,
        )
    if args.poses_out is not None:
        left_out = write_lidar_poses(
            args.poses_out, recording, result.poses, result.valid, args.pose_format
        )
        if left_out:
            lost = f"{left_out} scan(s) that did not localize left out (TUM)"
            note(args.command, f"{args.poses_out}: {lost}")
    summary = {"map": str(args.map), "map_instances": num_vertices, "map_build_s": build_s}
    judged = [r for r in records if "rte_m" in r]
    if judged:
        success = [
            r["valid"] and r["rte_m"] < SUCCESS_RTE_M and r["rre_deg"] < SUCCESS_RRE_DEG
            for r in judged
        ]
        summary["success_rate"] = float(np.mean(success))
        say(
            f"success (valid, RTE < {SUCCESS_RTE_M} m, RRE < {SUCCESS_RRE_DEG} deg): "
            f"{sum(success)}/{len(success)}"
        )
        if len(judged) < len(records):
            note(args.command, f"{len(records) - len(judged)} scan(s) without ground truth")
    if args.json:
        print(json.dumps({"summary": summary, "scans": records}, indent=2))
    return 0
