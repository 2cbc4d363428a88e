"""``jaxloc localize-lidar``: M2Loc on a HeLiPR/TripletLoc instance map and scan files."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc.cli._errors import InputError

#: Suffix of an instance-centroid scan file (lines ``class_id x y z``).
CENTROID_SUFFIX = ".txt"


class ScanInstances(NamedTuple):
    """Instance centroids of one scan: ``points`` (N, 3) float64 metres in the scan frame,
    ``labels`` (N,) int class ids, ``load_ms`` time to read (and cluster) the scan."""

    points: np.ndarray
    labels: np.ndarray
    load_ms: float


def _label_path(bin_path: Path) -> Path:
    """The ``.label`` of a SemanticKITTI ``.bin``: beside it, or in ``../labels/`` (the dataset's
    ``velodyne/`` + ``labels/`` layout)."""
    beside = bin_path.with_suffix(".label")
    if beside.exists():
        return beside
    dataset_layout = bin_path.parent.parent / "labels" / beside.name
    if dataset_layout.exists():
        return dataset_layout
    raise InputError(f"{bin_path}: no label file (looked for {beside} and {dataset_layout})")


def _read_number_rows(path: Path, columns: tuple[int, ...], what: str) -> list[np.ndarray]:
    """Rows of finite numbers of a text file (blank lines and ``#`` comments skipped), each with
    one of the allowed column counts."""
    rows = []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise InputError(f"{path}: not a text file ({what})") from error
    for line_number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) not in columns:
            allowed = " or ".join(str(c) for c in columns)
            raise InputError(
                f"{path}:{line_number}: expected {allowed} numbers ({what}), got {len(fields)}"
            )
        try:
            values = np.array([float(field) for field in fields])
        except ValueError as error:
            raise InputError(f"{path}:{line_number}: not a number in {line.strip()!r}") from error
        if not np.all(np.isfinite(values)):
            raise InputError(f"{path}:{line_number}: non-finite value in {line.strip()!r}")
        rows.append(values)
    return rows


def load_centroid_scan(path: Path, classes: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Read an instance-centroid scan file: lines ``class_id x y z`` (scan frame, metres).

    Returns (N, 3) float64 points and (N,) int64 class ids.

    Raises:
        InputError: wrong field count, non-numbers, non-integer or unknown class ids.
    """
    rows = _read_number_rows(path, (4,), "class_id x y z")
    table = np.asarray(rows, np.float64).reshape(-1, 4)
    labels = table[:, 0]
    if np.any(labels != np.round(labels)):
        raise InputError(f"{path}: class ids (first column) must be integers")
    unknown = sorted(set(labels.astype(int).tolist()) - set(classes))
    if unknown:
        raise InputError(f"{path}: unknown class ids {unknown}; expected some of {list(classes)}")
    return table[:, 1:4], labels.astype(np.int64)


def check_scan_path(path: Path) -> None:
    """Cheap checks before any work: the scan exists, its format is known, a ``.bin`` has labels."""
    if not path.exists():
        raise InputError(f"missing scan: {path}")
    if path.is_dir():
        return
    if path.suffix == ".bin":
        _label_path(path)
    elif path.suffix != CENTROID_SUFFIX:
        raise InputError(
            f"{path}: unknown scan format (expected .bin + .label, a {CENTROID_SUFFIX} "
            "centroid file, or a folder with instances/<class>.txt)"
        )


def load_scan(path: Path, classes: Sequence[int]) -> ScanInstances:
    """Instance centroids of a scan given as a SemanticKITTI ``.bin`` (+ ``.label``), a centroid
    ``.txt`` (``class_id x y z``), or a folder in the map's format (``instances/<class>.txt``)."""
    from jaxloc.io import load_instance_map, load_semantickitti_scan
    from jaxloc.m2loc import cluster_instances

    check_scan_path(path)
    start = time.perf_counter()
    try:
        if path.is_dir():
            instances = load_instance_map(path, tuple(classes))
            points, labels = instances.points, instances.labels
        elif path.suffix == ".bin":
            scan = load_semantickitti_scan(path, _label_path(path))
            instances = cluster_instances(scan.points, scan.labels)
            points, labels = instances.points, instances.labels
        else:
            points, labels = load_centroid_scan(path, classes)
    except ValueError as error:  # the library loaders' malformed-file errors
        raise InputError(str(error)) from error
    return ScanInstances(points, labels, 1e3 * (time.perf_counter() - start))


def load_poses(path: Path, count: int) -> np.ndarray:
    """Ground-truth ``T_map_scan`` per scan: one pose per line, 12 numbers (KITTI 3x4 row-major)
    or 16 (4x4 row-major), in the order of the scans. Returns (count, 4, 4) float64."""
    from jaxloc.io import read_poses

    try:
        poses = read_poses(path)
    except ValueError as error:
        raise InputError(str(error)) from error
    if len(poses) != count:
        raise InputError(f"{path}: {len(poses)} poses for {count} scan(s)")
    return poses


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


def describe_map(points: np.ndarray, labels: np.ndarray, config, normals, name: str):
    """:func:`jaxloc.m2loc.build_map` with its input errors reported as InputError."""
    from jaxloc.m2loc import build_map

    try:
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

    start = time.perf_counter()
    if path.is_file():
        if args.scales is not None or args.tripletloc:
            raise InputError(
                f"{path}: a saved map keeps the descriptors it was described with; drop "
                "--scales / --tripletloc (or describe the map folder again)"
            )
        try:
            triplet_map = load_triplet_map(path)
            config = dataclasses.replace(triplet_map.config, **_matching_options(args))
        except ValueError as error:  # MapFormatError, or an option the map cannot take
            raise InputError(f"{path}: {error}") from error
        if config.top_k > triplet_map.points.shape[0]:
            raise InputError(f"{path}: -k {config.top_k} exceeds the map's vertices")
        triplet_map = eqx.tree_at(lambda m: m.config, triplet_map, config)
    else:
        config = triplet_config(args)
        instances, normals = load_map_files(path, config.descriptor.classes, not args.no_rsn)
        triplet_map = describe_map(instances.points, instances.labels, config, normals, str(path))
    return triplet_map, time.perf_counter() - start


def check_save_path(path: Path | None) -> None:
    """Before any work: a ``--save-map`` path must name an ``.npz`` file."""
    if path is not None and path.suffix != ".npz":
        raise InputError(f"--save-map {path}: the file name must end in .npz")


def expand_scans(paths: Sequence[Path], every: int) -> tuple[list[Path], np.ndarray | None]:
    """SCAN arguments as scan paths: a sequence folder (``velodyne/*.bin`` + ``labels/``) gives
    every ``every``-th of its scans. Returns the paths and, when every argument is a sequence
    with ``poses.txt``, their ground-truth ``T_map_scan`` (else None)."""
    from jaxloc.io import is_sequence_dir, load_lidar_sequence

    scans, poses = [], []
    for path in paths:
        if not is_sequence_dir(path):
            check_scan_path(path)
            scans.append(path)
            poses.append(None)
            continue
        try:
            sequence = load_lidar_sequence(path, require_poses=False)
        except (ValueError, FileNotFoundError) as error:
            raise InputError(str(error)) from error
        chosen = list(sequence.bins[::every])
        scans += chosen
        truth = sequence.T_map_scan
        poses += [None] * len(chosen) if truth is None else list(truth[::every])
    known = all(pose is not None for pose in poses)
    return scans, (np.stack(poses) if known else None)


def localize_one(triplet_map, scan: ScanInstances):
    """Localize a scan; the first call of a query size compiles, so it is run again to time it.

    Returns the :class:`~jaxloc.m2loc.LocalizationResult` and the compile time (s, 0 if none).
    """
    from jaxloc.m2loc import localize_scan
    from jaxloc.m2loc._query import TRACE_COUNTS

    traces = sum(TRACE_COUNTS.values())
    start = time.perf_counter()
    result = localize_scan(triplet_map, None, scan.points, scan.labels)
    first = time.perf_counter() - start
    if sum(TRACE_COUNTS.values()) == traces:
        return result, 0.0
    start = time.perf_counter()
    result = localize_scan(triplet_map, None, scan.points, scan.labels)
    return result, max(first - (time.perf_counter() - start), 0.0)


def _scan_record(name: str, scan: ScanInstances, result, compile_s: float, T_gt) -> dict:
    from jaxloc.m2loc import localization_errors

    counts = {int(c): int(np.sum(scan.labels == c)) for c in np.unique(scan.labels)}
    record = {
        "scan": name,
        "instances": int(len(scan.points)),
        "instances_per_class": {str(c): n for c, n in counts.items()},
        "valid": bool(result.valid),
        "clique_size": int(result.clique_size),
        "scales_used": int(result.scales_used),
        "T_map_scan": np.round(result.pose, 6).tolist(),
        "load_ms": round(scan.load_ms, 3),
        "descriptor_ms": round(result.descriptor_time_ms, 3),
        "match_ms": round(result.match_time_ms, 3),
        "compile_s": round(compile_s, 3),
    }
    if T_gt is not None:
        rte, rre = localization_errors(result.pose, T_gt)
        record["rte_m"], record["rre_deg"] = float(rte), float(rre)
    return record


def _format_record(record: dict) -> str:
    classes = ", ".join(f"{n} x {c}" for c, n in record["instances_per_class"].items())
    lines = [
        f"{record['scan']}: {record['instances']} instances ({classes or 'none'}); "
        f"{'valid' if record['valid'] else 'NOT valid'}, clique {record['clique_size']}, "
        f"scales used {record['scales_used']}",
        "  T_map_scan =",
    ]
    lines += ["    " + " ".join(f"{v:12.4f}" for v in row) for row in record["T_map_scan"]]
    timing = (
        f"  time: load {record['load_ms']:.1f} ms, descriptors {record['descriptor_ms']:.1f} ms, "
        f"match + clique + pose {record['match_ms']:.1f} ms"
    )
    if record["compile_s"]:
        timing += f" (first scan of this size: +{record['compile_s']:.1f} s compile)"
    lines.append(timing)
    if "rte_m" in record:
        lines.append(f"  RTE {record['rte_m']:.3f} m, RRE {record['rre_deg']:.3f} deg")
    return "\n".join(lines)


def run_localize_lidar(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from jaxloc.io import save_triplet_map
    from jaxloc.m2loc import SUCCESS_RRE_DEG, SUCCESS_RTE_M

    check_config_args(args)
    check_save_path(args.save_map)
    if args.every < 1:
        raise InputError(f"--every must be >= 1, got {args.every}")
    scans, sequence_poses = expand_scans(args.scans, args.every)
    T_gt = sequence_poses if args.gt is None else load_poses(args.gt, len(scans))
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
    records = []
    show_bar = len(scans) > 1 and not args.no_progress
    for index, scan_path in enumerate(tqdm(scans, unit="scan", disable=not show_bar)):
        scan = load_scan(scan_path, classes)
        try:
            result, compile_s = localize_one(triplet_map, scan)
        except ValueError as error:  # duplicate points and the like: a problem of the scan
            raise InputError(f"{scan_path}: {error}") from error
        record = _scan_record(
            str(scan_path), scan, result, compile_s, None if T_gt is None else T_gt[index]
        )
        records.append(record)
        if not args.json:
            tqdm.write(_format_record(record))
    summary = {"map": str(args.map), "map_instances": num_vertices, "map_build_s": build_s}
    if T_gt is not None:
        success = [
            r["valid"] and r["rte_m"] < SUCCESS_RTE_M and r["rre_deg"] < SUCCESS_RRE_DEG
            for r in records
        ]
        summary["success_rate"] = float(np.mean(success))
        say(
            f"success (valid, RTE < {SUCCESS_RTE_M} m, RRE < {SUCCESS_RRE_DEG} deg): "
            f"{sum(success)}/{len(success)}"
        )
    if args.json:
        print(json.dumps({"summary": summary, "scans": records}, indent=2))
    return 0
