"""``jaxloc localize-lidar``: M2Loc on a HeLiPR/TripletLoc instance map and scan files or
sequences (SemanticKITTI, plain or HeLiPR layout)."""

from __future__ import annotations

import argparse
import json
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxloc.cli._errors import InputError
from jaxloc.cli._lidar_drive import DriveTracker, fuse_window, window_odometry, window_sizes
from jaxloc.cli._lidar_scans import (
    POSES_OUT_HELP,
    ScanInstances,
    ScanRef,
    attach_ground_truth,
    check_poses_out,
    expand_scans,
    load_scan,
    note,
    write_poses_out,
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


def check_config_args(args: argparse.Namespace) -> None:
    if args.k is not None and args.k < 1:
        raise InputError(f"-k must be >= 1, got {args.k}")
    if args.threshold is not None and not args.threshold > 0:
        raise InputError(f"--threshold must be > 0 metres, got {args.threshold}")
    if args.min_clique is not None and args.min_clique < 1:
        raise InputError(f"--min-clique must be >= 1, got {args.min_clique}")


def load_map_files(map_dir: Path, classes: Sequence[int], use_rsn: bool):
    """Read ``instances/<class>.txt`` and, when present and wanted, ``RSN/road_normal.txt``.

    Returns the :class:`~jaxloc.io.InstanceMap` and the RoadNormals (or None).
    """
    from jaxloc.io import load_instance_map, load_road_normals

    if not map_dir.is_dir():
        raise InputError(f"map folder not found: {map_dir}")
    for class_id in classes:
        if not (map_dir / "instances" / f"{class_id}.txt").is_file():
            raise InputError(f"{map_dir}: missing instances/{class_id}.txt (lines: id x y z)")
    try:
        instances = load_instance_map(map_dir, tuple(classes))
        normals = None
        if use_rsn and (map_dir / "RSN" / "road_normal.txt").is_file():
            normals = load_road_normals(map_dir)
    except ValueError as error:  # the loaders name file:line
        raise InputError(str(error)) from error
    return instances, normals


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


def open_map(path: Path, args: argparse.Namespace):
    """The described map of ``MAP``: a saved ``.npz`` (:func:`jaxloc.io.save_triplet_map`;
    the options that do not change descriptors override its settings) or a map folder (described
    with the options). Returns the TripletMap and the number of seconds it took."""
    import dataclasses

    import equinox as eqx

    from jaxloc.io import load_triplet_map
    from jaxloc.m2loc import fit_config_to_map

    start = time.perf_counter()
    if path.is_file():
        if args.scales is not None or args.tripletloc:
            raise InputError(
                f"{path}: a saved map keeps the descriptors it was described with; drop "
                "--scales / --tripletloc (or describe the map folder again)"
            )
        try:
            with notes_of_small_maps(args.command, str(path)):
                triplet_map = load_triplet_map(path)
                config = dataclasses.replace(triplet_map.config, **_matching_options(args))
                config = fit_config_to_map(config, int(triplet_map.points.shape[0]))
        except ValueError as error:  # MapFormatError, or an option the map cannot take
            raise InputError(f"{path}: {error}") from error
        triplet_map = eqx.tree_at(lambda m: m.config, triplet_map, config)
    else:
        config = triplet_config(args)
        instances, normals = load_map_files(path, config.descriptor.classes, not args.no_rsn)
        triplet_map = describe_map(
            instances.points, instances.labels, config, normals, str(path), args.command
        )
    return triplet_map, time.perf_counter() - start


def check_save_path(path: Path | None) -> None:
    """Before any work: a ``--save-map`` path must name an ``.npz`` file."""
    if path is not None and path.suffix != ".npz":
        raise InputError(f"--save-map {path}: the file name must end in .npz")


#: Query size bands already run in this process (their first run compiled or loaded them).
_RUN_BANDS: set[int] = set()


def localize_one(triplet_map, scan: ScanInstances):
    """Localize a scan; the first call of a query size band compiles (or loads from the cache)
    its programs, so it is run again to time the query alone.

    Returns the :class:`~jaxloc.m2loc.LocalizationResult` and the compile or load time (s, 0 if
    none).
    """
    from jaxloc.m2loc import localize_scan, query_capacity

    band = query_capacity(max(len(scan.points), 1), triplet_map.config)
    start = time.perf_counter()
    result = localize_scan(triplet_map, None, scan.points, scan.labels)
    first = time.perf_counter() - start
    if band in _RUN_BANDS:
        return result, 0.0
    _RUN_BANDS.add(band)
    start = time.perf_counter()
    result = localize_scan(triplet_map, None, scan.points, scan.labels)
    return result, max(first - (time.perf_counter() - start), 0.0)


def _scan_record(ref: ScanRef, scan: ScanInstances, result, compile_s: float) -> dict:
    from jaxloc.m2loc import localization_errors

    counts = {int(c): int(np.sum(scan.labels == c)) for c in np.unique(scan.labels)}
    record = {
        "scan": str(ref.path),
        "instances": int(len(scan.points)),
        "instances_per_class": {str(c): n for c, n in counts.items()},
        "valid": bool(result.valid),
        "ambiguous": bool(result.ambiguous),
        "clique_size": int(result.clique_size),
        "scales_used": int(result.scales_used),
        "T_map_scan": np.round(result.pose, 6).tolist(),
        "load_ms": round(scan.load_ms, 3),
        "descriptor_ms": round(result.descriptor_time_ms, 3),
        "match_ms": round(result.match_time_ms, 3),
        "compile_s": round(compile_s, 3),
    }
    if ref.timestamp is not None:
        record["timestamp_ns"] = int(ref.timestamp)
    if ref.T_gt is not None:
        rte, rre = localization_errors(result.pose, ref.T_gt)
        record["rte_m"], record["rre_deg"] = float(rte), float(rre)
    return record


def _why_not_valid(record: dict) -> str:
    """Why a pose that passed the clique and verification tests was refused ("" otherwise)."""
    from jaxloc.m2loc import WINDOW_MIN_CLIQUE

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

    from jaxloc.io import save_triplet_map
    from jaxloc.m2loc import SUCCESS_RRE_DEG, SUCCESS_RTE_M, WINDOW_MIN_CLIQUE, require_clique

    check_config_args(args)
    check_save_path(args.save_map)
    check_poses_out(args)
    if args.every < 1:
        raise InputError(f"--every must be >= 1, got {args.every}")
    least_scans, most_scans, instances = window_sizes(args)
    refs = expand_scans(args.scans, args)
    if args.gt is not None:
        refs = attach_ground_truth(refs, args.gt)
    triplet_map, build_s = open_map(args.map, args)
    if args.save_map is not None:
        save_triplet_map(triplet_map, args.save_map)
    classes = triplet_map.config.descriptor.classes
    num_vertices, has_rsn = int(triplet_map.points.shape[0]), triplet_map.has_rsn
    say = (lambda _: None) if args.json else print
    say(
        f"map {args.map}: {num_vertices} instances, "
        f"{'with' if has_rsn else 'without'} road normals, "
        f"{'loaded' if args.map.is_file() else 'described'} in {build_s:.1f} s"
    )
    odometry = window_odometry(refs, args)
    tracker = DriveTracker(triplet_map) if args.track else None
    records, results = [], []
    window: list[ScanInstances] = []
    show_bar = len(refs) > 1 and not args.no_progress
    for i, ref in enumerate(tqdm(refs, unit="scan", disable=not show_bar)):
        scan = load_scan(ref, classes)
        window = [scan, *window][:most_scans]  # newest first
        try:
            query, fused_scans = scan, 1
            if len(window) > 1:
                query, fused_scans = fuse_window(window, odometry[i::-1], least_scans, instances)
            if tracker is not None:
                T_prev_scan = np.linalg.inv(odometry[i - 1]) @ odometry[i] if i else np.eye(4)
                result, mode, compile_s = tracker.step(query, T_prev_scan)
            else:
                result, compile_s = localize_one(triplet_map, query)
                if fused_scans > 1:  # a window's pose must rest on more than the minimal set
                    refused = result.valid and result.clique_size < WINDOW_MIN_CLIQUE
                    result = require_clique(result, WINDOW_MIN_CLIQUE)
        except ValueError as error:  # duplicate points and the like: a problem of the scan
            raise InputError(f"{ref.path}: {error}") from error
        results.append(result)
        records.append(_scan_record(ref, scan, result, compile_s))
        if tracker is not None:
            records[-1]["track"] = mode
        if fused_scans > 1:
            records[-1]["fused_scans"] = fused_scans
            records[-1]["fused_instances"] = len(query.points)
            if tracker is None:
                records[-1]["small_clique"] = bool(refused)
        if not args.json:
            tqdm.write(_format_record(records[-1]))
    if args.poses_out is not None:
        write_poses_out(args, refs, results)
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
