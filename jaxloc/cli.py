"""The ``jaxloc`` command line.

* ``jaxloc demo``: localize a camera in an embedded synthetic room (SG2Loc, no downloads).
* ``jaxloc localize-lidar MAP_DIR SCAN...``: one-shot LiDAR localization (M2Loc) of scans in a
  HeLiPR/TripletLoc instance map; prints ``T_map_scan`` per scan, optionally RTE/RRE.
* ``jaxloc bench raycast|filter|triplet``: quick in-package speed checks after compilation.

Input problems (missing or malformed files, bad numbers) end with exit code 2 and a one-line
message on stderr, never a traceback. ``main(argv)`` returns the exit code, so the command can be
called in-process (tests do).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

# ----------------------------------------------------------------------------- errors


class InputError(Exception):
    """A problem with the user's files or arguments; reported in one line, exit code 2."""


def _fail(command: str, message: str) -> int:
    print(f"jaxloc {command}: error: {message}", file=sys.stderr)
    return 2


def _describe_os_error(error: OSError) -> str:
    if isinstance(error, FileNotFoundError):
        return f"missing file: {error.filename}"
    if isinstance(error, IsADirectoryError):
        return f"expected a file, got a directory: {error.filename}"
    return f"{error.strerror or error}: {error.filename}"


def _run_guarded(command: str, action: Callable[[], int]) -> int:
    """Run ``action``; turn input errors (InputError, OSError) into a message and exit code 2."""
    try:
        return action()
    except InputError as error:
        return _fail(command, str(error))
    except OSError as error:
        return _fail(command, _describe_os_error(error))


# ----------------------------------------------------------------------------- demo


def _demo_episode_config(args: argparse.Namespace):
    """The demo's room (4-5 m square, 15-18 objects) seen by an ``args.width x args.height``
    camera; ``bench filter`` uses it too (same scene and camera: shared compilations)."""
    from jaxloc.datasets import indoor

    return indoor.EpisodeConfig(
        room=indoor.RoomConfig(
            length_range=(4.0, 5.0), width_range=(4.0, 5.0), num_objects=(15, 18)
        ),
        sensor=indoor.SensorConfig(width=args.width, height=args.height),
    )


def _demo(args: argparse.Namespace) -> int:
    import jax

    from jaxloc import render_batch, stride_grid
    from jaxloc.datasets import indoor
    from jaxloc.metrics import summarize, yaw_pose_errors
    from jaxloc.resample import KLDConfig
    from jaxloc.sg2loc import SG2LocConfig, localize
    from jaxloc.viz import plot_rounds

    start = time.perf_counter()
    episode = indoor.make_episode(args.seed, args.frames, _demo_episode_config(args))
    scene = episode.scene
    print(
        f"room {episode.room.size[0]:.1f} x {episode.room.size[1]:.1f} m: "
        f"{scene.num_objects} objects, {scene.num_triangles} triangles, "
        f"map {scene.storage_mb():.2f} MB "
        f"({time.perf_counter() - start:.1f} s to build)"
    )
    camera = episode.sequence.camera
    grid = stride_grid(camera, 10, *episode.sequence.patch_shape)
    num_views = min(3, args.frames)
    views = render_batch(scene, jax.numpy.asarray(episode.poses_gt[:num_views]), camera, grid)
    for t in range(num_views):
        seen = np.unique(np.asarray(views.object_id[t]))
        depth = np.asarray(views.depth[t])
        depth = depth[np.isfinite(depth)]
        print(
            f"view {t + 1}: {np.sum(seen >= 0)} objects visible, depth {depth.min():.2f}-"
            f"{depth.max():.2f} m, {np.mean(np.asarray(views.valid[t])):.0%} rays hit"
        )
    sg2loc_config = SG2LocConfig(
        capacity=args.particles,
        strides=(8, 8),
        kld=KLDConfig(min_particles=min(300, args.particles), max_particles=args.particles),
    )
    result = localize(
        jax.random.key(args.seed), scene, episode.sequence, sg2loc_config, progress=True
    )
    pos_err, rot_err = yaw_pose_errors(np.asarray(result.poses), episode.poses_gt)
    for t, (p, r) in enumerate(zip(pos_err, rot_err, strict=True)):
        print(f"frame {t + 1}: position error {p:.3f} m, rotation error {r:.2f} deg")
    summary = summarize(pos_err[-1:], rot_err[-1:])
    print(
        f"last frame: {summary['median_pos_m']:.3f} m, {summary['median_rot_deg']:.2f} deg; "
        f"total {time.perf_counter() - start:.0f} s"
    )
    figure = plot_rounds(result, episode.poses_gt, args.out, np.asarray(scene.bounds))
    print(f"figure: {figure}")
    return 0


# ----------------------------------------------------------------------------- localize-lidar

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
    from jaxloc.triplet import cluster_instances, load_instance_map, load_semantickitti_scan

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
    rows = _read_number_rows(path, (12, 16), "a 3x4 or 4x4 pose, row-major")
    if len(rows) != count:
        raise InputError(f"{path}: {len(rows)} poses for {count} scan(s)")
    poses = np.tile(np.eye(4), (count, 1, 1))
    for index, row in enumerate(rows):
        poses[index].flat[: row.size] = row
    if not np.allclose(poses[:, 3], [0, 0, 0, 1]):
        raise InputError(f"{path}: the last row of a 4x4 pose must be 0 0 0 1")
    rotations = poses[:, :3, :3]
    gram_error = np.abs(rotations @ np.swapaxes(rotations, 1, 2) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((gram_error > 1e-3) | (np.linalg.det(rotations) < 0))
    if bad.size:
        raise InputError(f"{path}: pose {bad[0] + 1}: its 3x3 block must be a rotation")
    return poses


def _triplet_config(args: argparse.Namespace):
    from jaxloc.triplet import m2loc_config, tripletloc_config

    options = dict(
        top_k=args.k,
        consistency_threshold=args.threshold,
        min_clique=args.min_clique,
        use_rsn=not args.no_rsn,
    )
    if args.tripletloc:
        return tripletloc_config(**options)
    return m2loc_config(args.scales, **options)


def _check_config_args(args: argparse.Namespace) -> None:
    if args.k < 1:
        raise InputError(f"-k must be >= 1, got {args.k}")
    if not args.threshold > 0:
        raise InputError(f"--threshold must be > 0 metres, got {args.threshold}")
    if args.min_clique < 1:
        raise InputError(f"--min-clique must be >= 1, got {args.min_clique}")


def load_map_files(map_dir: Path, classes: Sequence[int], use_rsn: bool):
    """Read ``instances/<class>.txt`` and, when present and wanted, ``RSN/road_normal.txt``.

    Returns the :class:`~jaxloc.triplet.InstanceMap` and the RoadNormals (or None).
    """
    from jaxloc.triplet import load_instance_map, load_road_normals

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
    """:func:`jaxloc.triplet.build_map` with its input errors reported as InputError."""
    from jaxloc.triplet import build_map

    try:
        return build_map(points, labels, config, normals)
    except ValueError as error:
        raise InputError(f"map {name}: {error}") from error


def _localize_one(triplet_map, scan: ScanInstances):
    """Localize a scan; the first call of a query size compiles, so it is run again to time it.

    Returns the :class:`~jaxloc.triplet.LocalizationResult` and the compile time (s, 0 if none).
    """
    from jaxloc.triplet import localize_scan
    from jaxloc.triplet._pipeline import TRACE_COUNTS

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
    from jaxloc.triplet import localization_errors

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


def _localize_lidar(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from jaxloc.triplet._metrics import SUCCESS_RRE_DEG, SUCCESS_RTE_M

    _check_config_args(args)
    for scan_path in args.scans:
        check_scan_path(scan_path)
    T_gt = None if args.gt is None else load_poses(args.gt, len(args.scans))
    config = _triplet_config(args)
    start = time.perf_counter()
    instances, normals = load_map_files(args.map_dir, config.descriptor.classes, not args.no_rsn)
    triplet_map = describe_map(
        instances.points, instances.labels, config, normals, str(args.map_dir)
    )
    build_s = time.perf_counter() - start
    num_vertices, has_rsn = len(instances.points), normals is not None
    say = (lambda _: None) if args.json else print
    say(
        f"map {args.map_dir}: {num_vertices} instances, "
        f"{'with' if has_rsn else 'without'} road normals, described in {build_s:.1f} s"
    )
    records = []
    show_bar = len(args.scans) > 1 and not args.no_progress
    for index, scan_path in enumerate(tqdm(args.scans, unit="scan", disable=not show_bar)):
        scan = load_scan(scan_path, config.descriptor.classes)
        try:
            result, compile_s = _localize_one(triplet_map, scan)
        except ValueError as error:  # duplicate points and the like: a problem of the scan
            raise InputError(f"{scan_path}: {error}") from error
        record = _scan_record(
            str(scan_path), scan, result, compile_s, None if T_gt is None else T_gt[index]
        )
        records.append(record)
        if not args.json:
            tqdm.write(_format_record(record))
    summary = {"map": str(args.map_dir), "map_instances": num_vertices, "map_build_s": build_s}
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


# ----------------------------------------------------------------------------- bench


def _timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Best-of-``repeats`` wall seconds and the process CPU seconds of that run."""
    best = (np.inf, np.inf)
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        elapsed = (time.perf_counter() - wall, time.process_time() - cpu)
        best = min(best, elapsed)
    return best


def _check_positive(args: argparse.Namespace, names: Sequence[str]) -> None:
    for name in names:
        if getattr(args, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")


def _bench_raycast(args: argparse.Namespace) -> int:
    import jax

    from jaxloc import render_batch, stride_grid
    from jaxloc.camera import Camera
    from jaxloc.datasets.indoor import RoomConfig, make_room, scene_graph

    _check_positive(args, ("poses", "width", "height", "stride", "objects", "vertices", "repeats"))
    room = make_room(
        args.seed,
        RoomConfig(num_objects=(args.objects, args.objects), vertex_range=(args.vertices,) * 2),
    )
    scene = scene_graph(room)
    camera = Camera.from_fov(args.width, args.height, 60.0)
    grid = stride_grid(camera, args.stride)
    rng = np.random.default_rng(args.seed)
    lx, ly, _ = room.size
    poses = np.column_stack(
        [
            rng.uniform(0.3, lx - 0.3, args.poses),
            rng.uniform(0.3, ly - 0.3, args.poses),
            rng.uniform(1.2, 1.8, args.poses),
            rng.uniform(-np.pi, np.pi, args.poses),
        ]
    ).astype(np.float32)
    start = time.perf_counter()
    compiled = jax.jit(render_batch).lower(scene, poses, camera, grid).compile()
    compile_s = time.perf_counter() - start
    wall, cpu = _timed(
        lambda: jax.block_until_ready(compiled(scene, poses, camera, grid)), args.repeats
    )
    rays = args.poses * grid.uv.shape[0]
    print(
        f"raycast (render_batch): {scene.num_objects} objects, {scene.num_triangles} triangles; "
        f"{args.poses} poses x {grid.uv.shape[0]} rays ({args.width}x{args.height}, "
        f"stride {args.stride}) = {rays} rays"
    )
    print(f"  compile {compile_s:.2f} s; best of {args.repeats}: {wall * 1e3:.1f} ms")
    per_cpu_s = rays / max(cpu, 1e-9) / 1e6
    print(f"  {rays / wall / 1e6:.3f} M rays/s (wall), {per_cpu_s:.3f} M rays per CPU-second")
    return 0


def _bench_filter(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.camera import stride_grid
    from jaxloc.datasets import indoor
    from jaxloc.resample import KLDConfig
    from jaxloc.sg2loc import SG2LocConfig, localize

    _check_positive(args, ("particles", "frames", "width", "height", "stride"))
    start = time.perf_counter()
    episode = indoor.make_episode(args.seed, args.frames, _demo_episode_config(args))
    build_s = time.perf_counter() - start
    scene, sequence = episode.scene, episode.sequence
    config = SG2LocConfig(
        capacity=args.particles,
        strides=(args.stride,),
        kld=KLDConfig(min_particles=min(300, args.particles), max_particles=args.particles),
    )

    def run(seed: int) -> None:  # the demo's path: one jitted step per frame
        result = localize(jax.random.key(seed), scene, sequence, config, progress=True)
        jax.block_until_ready(result.poses)

    start = time.perf_counter()
    run(args.seed)
    first_s = time.perf_counter() - start
    wall, cpu = _timed(lambda: run(args.seed + 1), 1)
    rays = stride_grid(sequence.camera, args.stride).uv.shape[0]
    print(
        f"filter (SG2Loc, one round): {args.particles} particles x {rays} rays "
        f"({args.width}x{args.height}, stride {args.stride}), {scene.num_objects} objects, "
        f"{scene.num_triangles} triangles (episode built in {build_s:.1f} s)"
    )
    print(f"  compile {max(first_s - wall, 0.0):.2f} s")
    print(
        f"  {wall / args.frames:.4f} s/frame wall, {cpu / args.frames:.4f} s/frame CPU "
        f"(mean over {args.frames} frames)"
    )
    return 0


def _bench_triplet(args: argparse.Namespace) -> int:
    from jaxloc.datasets.outdoor import make_outdoor_world, make_query
    from jaxloc.triplet import localization_errors
    from jaxloc.triplet._metrics import SUCCESS_RRE_DEG, SUCCESS_RTE_M

    _check_positive(args, ("queries", "max_kept", "blocks"))
    _check_config_args(args)
    config = _triplet_config(args)
    if args.map is not None:
        instances, normals = load_map_files(args.map, config.descriptor.classes, True)
        if normals is None:
            raise InputError(f"{args.map}: queries are drawn on RSN/road_normal.txt, missing")
        points, labels, name = instances.points, instances.labels, str(args.map)
    else:
        world = make_outdoor_world(args.world, seed=args.seed, blocks=args.blocks, bridge_length=0)
        points, labels, normals = world.points, world.labels, world.road_normals
        name = f"synthetic {args.world} world ({args.blocks}x{args.blocks} blocks)"
    triplet_map = describe_map(points, labels, config, None if args.no_rsn else normals, name)
    num_vertices = len(points)
    rng = np.random.default_rng(args.seed + 1)
    queries = [
        make_query(points, labels, normals, rng, max_kept=args.max_kept)
        for _ in range(args.queries)
    ]
    records = []
    compile_s = 0.0
    for query in queries:
        scan = ScanInstances(query.points, query.labels, 0.0)
        result, compiled = _localize_one(triplet_map, scan)
        compile_s += compiled
        rte, rre = localization_errors(result.pose, query.T_map_scan)
        success = result.valid and rte < SUCCESS_RTE_M and rre < SUCCESS_RRE_DEG
        records.append((result.descriptor_time_ms, result.match_time_ms, success))
    desc, match, success = (np.array(column) for column in zip(*records, strict=True))
    sizes = [len(q.points) for q in queries]
    print(
        f"triplet ({'TripletLoc' if args.tripletloc else f'M2Loc, {args.scales} scale(s)'}, "
        f"k={args.k}): {name}, {num_vertices} map instances; {args.queries} queries of "
        f"{min(sizes)}-{max(sizes)} instances"
    )
    print(f"  compile {compile_s:.2f} s")
    print(
        f"  descriptors {np.median(desc):.2f} ms/query, match + clique + pose "
        f"{np.median(match):.2f} ms/query (medians); success {success.mean():.0%}"
    )
    return 0


# ----------------------------------------------------------------------------- parser

_MAIN_EPILOG = """\
examples:
  jaxloc demo                                    # camera localization in a synthetic room
  jaxloc localize-lidar maps/KAIST04 scans/000000.bin
  jaxloc localize-lidar maps/KAIST04 scans/*.bin --gt poses.txt --json > result.json
  jaxloc bench raycast --poses 64
  jaxloc bench triplet --queries 20

Run `jaxloc COMMAND --help` for the options of a command.
"""

_LIDAR_DESCRIPTION = """\
One-shot global localization of LiDAR scans in an instance map (M2Loc / TripletLoc).

MAP_DIR is a HeLiPR/TripletLoc instance map folder:
  MAP_DIR/instances/15.txt, 17.txt, 18.txt   lines "id x y z" (trunks, poles, traffic signs;
                                             map frame, metres)
  MAP_DIR/RSN/road_normal.txt                optional, lines "x y nx ny nz std_deg": road-surface
                                             normals, used as a roll/pitch prior

Each SCAN is one of:
  NAME.bin       a SemanticKITTI scan (float32 x y z intensity); its labels NAME.label are read
                 from beside it or from ../labels/ (the dataset layout). Instances are clustered
                 from the trunk, pole and traffic-sign points (TripletLoc's recipe).
  NAME.txt       instance centroids already extracted: lines "class_id x y z" (class_id 15, 17
                 or 18; scan frame, metres; '#' starts a comment)
  a folder       instances/15.txt, 17.txt, 18.txt in the map's own format

The map's descriptors are built once; every scan is then described, matched, and registered.
Per scan it prints the 4x4 T_map_scan (p_map = T_map_scan @ p_scan), whether it is valid, the
size of the maximum clique of consistent matches, and the times. The first scan of each
instance count band (32, 64, ...) also compiles (reported separately).
"""

_LIDAR_EPILOG = """\
examples:
  jaxloc localize-lidar ../shared/data/helipr_instance_maps/KAIST04 \\
      ../shared/data/semantickitti_scan/000000.bin
  jaxloc localize-lidar MAP scan_centroids.txt --scales 1 -k 10
  jaxloc localize-lidar MAP scans/*.txt --gt poses.txt --json > result.json

--gt FILE: one ground-truth T_map_scan per line, in the order of the scans: 12 numbers (KITTI
3x4, row-major) or 16 (4x4, row-major). Then RTE (m) and RRE (deg) are printed, and the success
rate (valid, RTE < 7.5 m, RRE < 10 deg).

exit status: 0 on success, 2 on missing or malformed files or bad options (one-line message).
"""

_BENCH_EPILOG = """\
examples:
  jaxloc bench raycast                           # rays/s of render_batch
  jaxloc bench raycast --poses 256 --width 320 --height 180
  jaxloc bench filter --particles 2500           # s/frame of one SG2Loc filter step
  jaxloc bench triplet --queries 50 --scales 3   # ms/query of M2Loc
  jaxloc bench triplet --map ../shared/data/helipr_instance_maps/KAIST04

Times are after compilation (compile time is printed separately); wall and process CPU time
are both given where the machine may be shared. The full comparisons with peers (Embree,
networkx) are the scripts in benchmarks/ of the repository.
"""


def _add_triplet_options(parser: argparse.ArgumentParser, scales: int, k: int) -> None:
    group = parser.add_argument_group("localization settings")
    group.add_argument(
        "--scales",
        type=int,
        choices=(1, 2, 3),
        default=scales,
        help=f"M2Loc descriptor scales: [0,20], (20,30], (30,40] m (default {scales})",
    )
    group.add_argument(
        "--tripletloc",
        action="store_true",
        help="use TripletLoc's one-scale descriptor (edge lengths) instead of M2Loc's",
    )
    group.add_argument(
        "-k", type=int, default=k, help=f"map matches per scan instance and scale (default {k})"
    )
    group.add_argument(
        "--threshold",
        type=float,
        default=1.0,
        help="consistency threshold of the match graph, metres (default 1.0)",
    )
    group.add_argument(
        "--min-clique",
        type=int,
        default=10,
        help="add scales while the clique is smaller than this (M2Loc's T, default 10)",
    )
    group.add_argument("--no-rsn", action="store_true", help="ignore the road-normal prior")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``jaxloc`` command (subcommands demo, localize-lidar, bench)."""
    parser = argparse.ArgumentParser(
        prog="jaxloc",
        description="Differentiable global localization against compact maps.",
        epilog=_MAIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND", help="what to run (COMMAND --help)"
    )
    demo = commands.add_parser(
        "demo",
        help="localize a camera in an embedded synthetic room (no downloads)",
        description="Builds a synthetic room and a query sequence, renders a few views, runs the "
        "coarse-to-fine SG2Loc particle filter with a progress bar, prints per-frame errors and "
        "writes a figure of the particles per round and frame.",
        epilog="examples:\n  jaxloc demo\n  jaxloc demo --seed 3 --frames 10 --out demo.png",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument("--seed", type=int, default=1, help="room and sequence seed (default 1)")
    demo.add_argument("--frames", type=int, default=6, help="frames in the sequence (default 6)")
    demo.add_argument(
        "--particles", type=int, default=1000, help="particle capacity (default 1000)"
    )
    demo.add_argument("--width", type=int, default=160, help="image width, pixels (default 160)")
    demo.add_argument("--height", type=int, default=90, help="image height, pixels (default 90)")
    demo.add_argument("--out", type=Path, default=Path("jaxloc_demo.png"), help="figure path (PNG)")

    lidar = commands.add_parser(
        "localize-lidar",
        help="localize LiDAR scans in an instance map (M2Loc): pose and metrics per scan",
        description=_LIDAR_DESCRIPTION,
        epilog=_LIDAR_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    lidar.add_argument("map_dir", type=Path, metavar="MAP_DIR", help="instance map folder")
    lidar.add_argument("scans", type=Path, nargs="+", metavar="SCAN", help="scan file(s)")
    lidar.add_argument("--gt", type=Path, help="ground-truth poses, one per scan (see below)")
    lidar.add_argument("--json", action="store_true", help="print one JSON document instead")
    lidar.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_triplet_options(lidar, scales=3, k=25)

    bench = commands.add_parser(
        "bench",
        help="quick speed checks: raycast (rays/s), filter (s/frame), triplet (ms/query)",
        description="Quick in-package benchmarks on synthetic data (no Embree, no downloads).",
        epilog=_BENCH_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    kinds = bench.add_subparsers(
        dest="bench", required=True, metavar="WHAT", help="what to time (WHAT --help: options)"
    )
    raycast = kinds.add_parser(
        "raycast",
        help="rays/s of render_batch in a synthetic room",
        description="Times jax.jit(render_batch) on random poses in a synthetic room.",
    )
    raycast.add_argument("--poses", type=int, default=64, help="camera poses (default 64)")
    raycast.add_argument("--width", type=int, default=480, help="image width (default 480)")
    raycast.add_argument("--height", type=int, default=270, help="image height (default 270)")
    raycast.add_argument("--stride", type=int, default=10, help="pixel stride (default 10)")
    raycast.add_argument("--objects", type=int, default=20, help="furniture objects (default 20)")
    raycast.add_argument(
        "--vertices", type=int, default=600, help="vertices per object mesh (default 600)"
    )
    raycast.add_argument("--repeats", type=int, default=3, help="timed runs, best of (default 3)")
    raycast.add_argument("--seed", type=int, default=0, help="room and pose seed (default 0)")

    filter_ = kinds.add_parser(
        "filter",
        help="s/frame of the SG2Loc particle filter",
        description="Times SG2Loc (one round: render, score, resample per frame) on the demo's "
        "synthetic room, after compilation.",
    )
    filter_.add_argument("--particles", type=int, default=1000, help="capacity (default 1000)")
    filter_.add_argument("--frames", type=int, default=3, help="frames timed (default 3)")
    filter_.add_argument("--width", type=int, default=160, help="image width (default 160)")
    filter_.add_argument("--height", type=int, default=90, help="image height (default 90)")
    filter_.add_argument("--stride", type=int, default=8, help="pixel stride (default 8)")
    filter_.add_argument("--seed", type=int, default=1, help="episode seed (default 1)")

    triplet = kinds.add_parser(
        "triplet",
        help="ms/query of M2Loc on a synthetic world or a map folder",
        description="Times localize_scan on seeded scan-like queries cut from the map "
        "(jaxloc.datasets.outdoor.make_query), and reports the success rate.",
    )
    triplet.add_argument("--queries", type=int, default=20, help="queries (default 20)")
    triplet.add_argument(
        "--max-kept",
        type=int,
        default=24,
        help="map instances kept per query (default 24: with the spurious ones at most 31, "
        "so all queries share one compilation)",
    )
    triplet.add_argument("--map", type=Path, help="instance map folder (default: synthetic world)")
    triplet.add_argument(
        "--world", choices=("sparse", "dense"), default="dense", help="synthetic world kind"
    )
    triplet.add_argument("--blocks", type=int, default=2, help="synthetic world: blocks per side")
    triplet.add_argument("--seed", type=int, default=0, help="world and query seed (default 0)")
    _add_triplet_options(triplet, scales=1, k=25)
    return parser


_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "demo": _demo,
    "localize-lidar": _localize_lidar,
    "bench raycast": _bench_raycast,
    "bench filter": _bench_filter,
    "bench triplet": _bench_triplet,
}


def main(argv: list[str] | None = None) -> int:
    """Run the ``jaxloc`` command with ``argv`` (default ``sys.argv[1:]``); returns the exit code.

    Usage errors (unknown options) exit through argparse with status 2.
    """
    args = build_parser().parse_args(argv)
    name = args.command if args.command != "bench" else f"bench {args.bench}"
    return _run_guarded(name, lambda: _COMMANDS[name](args))


if __name__ == "__main__":
    sys.exit(main())
