"""A drive in one call: every scan of a recording localized, alone, through the fused window of
the last scans (``grow_window``) or tracked (:class:`~jaxloc.m2loc.Tracker`).

:func:`localize_drive` walks the scans oldest first. Scan ``i`` is localized as its query: the
scan itself, or with ``accumulate = K > 1`` the fusion of its last K scans through the odometry
(:func:`drive_window`: grown with older ones, up to ``DriveConfig.most_scans``, while it holds
fewer than ``DriveConfig.min_instances`` instances; a window of one scan, at the start of a
drive, is the scan). Without tracking each query is localized globally
(:func:`~jaxloc.m2loc.localize_scan`), a fused window's pose refused on a clique below
``DriveConfig.min_clique`` (``require_clique``); with ``track=True`` the queries
are stepped through a :class:`~jaxloc.m2loc.Tracker` with the odometry between consecutive scans.

Host-side: scans are read one at a time from the source (a recording of
:func:`jaxloc.io.open_lidar_recording`, or any :class:`ScanSource`, or a list of
``(points, labels)`` scans); queries run at the power-of-two capacity band of their size, so a
drive compiles once per band. The first query of each band in a call runs twice (the same
result: the programs are pure) to tell its compile or cache-load time from its run time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import NamedTuple, Protocol, runtime_checkable

import equinox as eqx
import jax
import numpy as np

from jaxloc.m2loc._accumulation import (
    MERGE_RADIUS,
    WINDOW_MIN_CLIQUE,
    WINDOW_MIN_INSTANCES,
    FusedScans,
    grow_window,
    require_clique,
)
from jaxloc.m2loc._config import TripletConfig
from jaxloc.m2loc._localization import (
    LocalizationResult,
    localize_scan,
    pad_scan,
    query_capacity,
)
from jaxloc.m2loc._map import TripletMap, with_config
from jaxloc.m2loc._tracking import LOST, RELOCALIZED, TrackConfig, Tracker, TrackStatus, track_step

#: The name of each :attr:`DriveResult.status` value (``STATUS_NAMES[TRACKED] == "tracked"``).
STATUS_NAMES = tuple(status.name.lower() for status in TrackStatus)


class ScanInstances(NamedTuple):
    """Instance centroids of one scan: ``points`` (M, 3) float64 metres in the scan frame,
    ``labels`` (M,) int class ids."""

    points: np.ndarray
    labels: np.ndarray


@runtime_checkable
class ScanSource(Protocol):
    """What :func:`localize_drive` reads a drive from (:class:`jaxloc.io.LidarRecording` is one).

    ``len(source)`` scans, oldest first; ``instances(i, classes)`` reads scan ``i``'s instance
    centroids of the map's ``classes``; ``name(i)`` names it in errors; ``poses`` (N, 4, 4)
    ``T_map_scan`` or None, and ``has_pose`` (N,) bool where ``poses`` holds one: the odometry
    when :func:`localize_drive` is given none.
    """

    poses: np.ndarray | None
    has_pose: np.ndarray

    def __len__(self) -> int: ...

    def instances(self, index: int, classes: tuple[int, ...]) -> ScanInstances: ...

    def name(self, index: int) -> str: ...


class DriveConfig(eqx.Module):
    """How :func:`localize_drive` builds windows and tracks (host-side settings).

    Attributes:
        most_scans: the most scans a window of ``accumulate = K`` grows to (None: 2K).
        min_instances: a window grows with older scans while its fusion holds fewer instances
            (``WINDOW_MIN_INSTANCES``; 0: exactly K scans).
        min_clique: the smallest clique a fused window's global pose may rest on
            (``WINDOW_MIN_CLIQUE``; single scans keep the map's
            ``min_inliers``; not used when tracking).
        merge_radius: metres; instances of one class this close after odometry are one object.
        track: the :class:`~jaxloc.m2loc.TrackConfig` of ``track=True``.
    """

    most_scans: int | None = eqx.field(static=True, default=None)
    min_instances: int = eqx.field(static=True, default=WINDOW_MIN_INSTANCES)
    min_clique: int = eqx.field(static=True, default=WINDOW_MIN_CLIQUE)
    merge_radius: float = eqx.field(static=True, default=MERGE_RADIUS)
    track: TrackConfig = TrackConfig()

    def __check_init__(self) -> None:
        if self.most_scans is not None and self.most_scans < 1:
            raise ValueError(f"most_scans must be >= 1, got {self.most_scans}")
        if self.min_instances < 0 or self.min_clique < 1 or not self.merge_radius >= 0:
            raise ValueError(
                "need min_instances >= 0, min_clique >= 1 and merge_radius >= 0, got "
                f"{self.min_instances}, {self.min_clique}, {self.merge_radius}"
            )


class DriveStep(NamedTuple):
    """One scan of a drive as :func:`localize_drive` localized it (what ``progress`` receives).

    Attributes:
        result: the :class:`~jaxloc.m2loc.LocalizationResult` of the scan's query (its ``pose``
            the scan's ``T_map_scan``). Tracking: ``clique_size`` and ``num_associations`` are the
            local associations (0 for a global step), ``match_time_ms`` the whole step.
        status: a :class:`~jaxloc.m2loc.TrackStatus`: ``TRACKED``, ``RELOCALIZED`` (a global
            pose; without tracking every valid pose), ``LOST`` (no pose) or ``PENDING`` (tracking:
            a global pose awaiting the next scan's confirmation, not valid).
        instances: the scan's own instance centroids.
        fused: the fused window localized instead (None: the scan alone).
        small_clique: a fused window's valid pose was refused for resting on a clique below
            ``DriveConfig.min_clique``.
        load_ms: time to read (and cluster) the scan.
        compile_s: compile or cache-load time of the query's programs (0 after the first query of
            its size band).
    """

    result: LocalizationResult
    status: int
    instances: ScanInstances
    fused: FusedScans | None
    small_clique: bool
    load_ms: float
    compile_s: float


class DriveResult(NamedTuple):
    """Result of :func:`localize_drive` (host numpy values, one entry per scan, oldest first).

    Attributes:
        poses: (N, 4, 4) float64 ``T_map_scan`` (identity where not valid).
        valid: (N,) bool.
        status: (N,) int32 :class:`~jaxloc.m2loc.TrackStatus` values (``TRACKED``,
            ``RELOCALIZED``, ``LOST`` or ``PENDING``; ``TrackStatus(s).name``).
        fused_scans: (N,) int64 scans fused into each query (1: the scan alone).
        load_ms: (N,) float64 read time; localize_ms: (N,) float64 descriptor + match (or
            tracking step) time; compile_s: (N,) float64 compile or load time.
        steps: the :class:`DriveStep` of each scan (instances, fused windows, full results).
    """

    poses: np.ndarray
    valid: np.ndarray
    status: np.ndarray
    fused_scans: np.ndarray
    load_ms: np.ndarray
    localize_ms: np.ndarray
    compile_s: np.ndarray
    steps: tuple[DriveStep, ...]


def drive_window(
    points: Sequence[np.ndarray],
    labels: Sequence[np.ndarray],
    odometry: np.ndarray,
    end: int,
    least_scans: int,
    most_scans: int | None = None,
    min_instances: int = WINDOW_MIN_INSTANCES,
    merge_radius: float = MERGE_RADIUS,
) -> FusedScans:
    """The fused window of scan ``end`` of a drive (its query under ``accumulate``).

    Args:
        points: per scan of the drive, oldest first, its instance centroids (M_i, 3) (scan
            frame, metres), at least the scans up to ``end``.
        labels: per scan, the centroids' (M_i,) class ids.
        odometry: (S, 4, 4) pose of each scan in one fixed frame (``T_odom_scan``; only the
            relative poses matter).
        end: the window's newest scan.
        least_scans: K, the newest scans always fused (fewer at the start of a drive).
        most_scans: the most scans the window grows to (None: K).
        min_instances: grow while the fusion holds fewer instances (:func:`grow_window`).
        merge_radius: as :func:`~jaxloc.m2loc.fuse_scans`.

    Returns:
        :class:`~jaxloc.m2loc.FusedScans` in scan ``end``'s frame; ``members.shape[1]`` scans,
        newest first, were fused.
    """
    most = least_scans if most_scans is None else most_scans
    window = range(end, max(end - most, -1), -1)  # newest first
    newest = np.linalg.inv(odometry[end])
    return grow_window(
        [points[j] for j in window],
        [labels[j] for j in window],
        np.stack([newest @ odometry[j] for j in window]),
        least_scans,
        min_instances,
        merge_radius,
    )


class _ScanList:
    """A list of scans, each ``(points, labels)`` or anything with ``.points`` and ``.labels``
    (:class:`ScanInstances`, :class:`~jaxloc.m2loc.Instances`, a synthetic query), as a
    :class:`ScanSource` without poses."""

    def __init__(self, scans: Sequence) -> None:
        self.scans = list(scans)
        self.poses = None
        self.has_pose = np.zeros(len(self.scans), bool)

    def __len__(self) -> int:
        return len(self.scans)

    def instances(self, index: int, classes: tuple[int, ...]) -> ScanInstances:
        scan = self.scans[index]
        if hasattr(scan, "points") and hasattr(scan, "labels"):
            return ScanInstances(scan.points, scan.labels)
        points, labels = scan
        return ScanInstances(points, labels)

    def name(self, index: int) -> str:
        return f"scan {index}"


def first_query_capacity(source: ScanSource, config: TripletConfig) -> tuple[int, ...]:
    """``(capacity,)``, the padded size of the query of the first scan of ``source`` alone (for
    :func:`~jaxloc.m2loc.prepare_queries` to compile its programs ahead), or () where no query
    program would run for it: no scan, fewer than 3 instances, or a scan that does not read or
    that :func:`~jaxloc.m2loc.localize_scan` refuses (its error comes when it is localized)."""
    if not len(source):
        return ()
    try:
        scan = source.instances(0, config.descriptor.classes)
        padded = pad_scan(scan.points, scan.labels, config)
    except (OSError, ValueError):
        return ()
    return (padded.points.shape[0],) if len(scan.points) >= 3 else ()


def _window_sizes(accumulate: int, config: DriveConfig) -> tuple[int, int, int]:
    """(K, M, N) of a drive: (1, 1, 0) for single scans."""
    if accumulate < 1:
        raise ValueError(f"accumulate must be >= 1, got {accumulate}")
    if accumulate == 1:
        return 1, 1, 0
    most = 2 * accumulate if config.most_scans is None else config.most_scans
    if most < accumulate:
        raise ValueError(f"most_scans must be >= accumulate ({accumulate}), got {most}")
    return accumulate, most, config.min_instances


def _odometry(source: ScanSource, odometry, count: int) -> np.ndarray:
    """(S, 4, 4) odometry poses: the given ones, else the source's (a pose for every scan)."""
    if odometry is None:
        if source.poses is None or not np.all(source.has_pose):
            missing = np.flatnonzero(~np.asarray(source.has_pose, bool))
            first = f" (first: {source.name(int(missing[0]))})" if missing.size else ""
            raise ValueError(
                f"accumulate > 1 and track need an odometry pose for every scan; the scans' own "
                f"poses miss {missing.size} of {count}{first}: pass odometry="
            )
        odometry = source.poses
    odometry = np.asarray(odometry, np.float64)
    if odometry.shape != (count, 4, 4) or not np.all(np.isfinite(odometry)):
        raise ValueError(f"odometry must be ({count}, 4, 4) finite poses, got {odometry.shape}")
    return odometry


def _first_in_band(bands: set[int], band: int) -> bool:
    if band in bands:
        return False
    bands.add(band)
    return True


def _localize(triplet_map: TripletMap, query: ScanInstances, bands: set[int]):
    """:func:`localize_scan` of a query; the first of a size band runs twice (to time the
    query alone). Returns the result and the compile or load time (s)."""
    band = query_capacity(max(len(query.points), 1), triplet_map.config)
    start = time.perf_counter()
    result = localize_scan(triplet_map, None, query.points, query.labels)
    first = time.perf_counter() - start
    if not _first_in_band(bands, band):
        return result, 0.0
    start = time.perf_counter()
    result = localize_scan(triplet_map, None, query.points, query.labels)
    return result, max(first - (time.perf_counter() - start), 0.0)


def _track(tracker: Tracker, state, query: ScanInstances, T_prev_scan, bands: set[int]):
    """One :func:`track_step` (the first of a size band run twice from the same state); returns
    the new state, the result as a LocalizationResult, the mode and the compile time (s)."""
    config = tracker.triplet_map.config
    band = query_capacity(max(len(query.points), 1), config)
    padded = pad_scan(query.points, query.labels, config, band)

    def run():
        start = time.perf_counter()
        out = jax.block_until_ready(track_step(tracker, state, padded, T_prev_scan))
        return out, time.perf_counter() - start

    (new_state, out), seconds = run()
    compile_s = 0.0
    if _first_in_band(bands, band):
        (new_state, out), again = run()
        compile_s, seconds = max(seconds - again, 0.0), again
    result = LocalizationResult(
        pose=np.asarray(out.T_map_scan, np.float64),
        valid=bool(out.valid),
        clique_size=int(out.num_associations),
        inliers=np.zeros((0, 2), np.int64),
        scales_used=0,
        clique_exact=False,
        num_associations=int(out.num_associations),
        inlier_fraction=float(out.inlier_fraction),
        descriptor_time_ms=0.0,
        match_time_ms=1e3 * seconds,
    )
    return new_state, result, int(out.mode), compile_s


def localize_drive(
    triplet_map: TripletMap,
    scans: ScanSource | Sequence,
    *,
    odometry: np.ndarray | None = None,
    accumulate: int = 1,
    track: bool = False,
    config: DriveConfig | None = None,
    query_config: TripletConfig | None = None,
    progress: Callable[[int, DriveStep], None] | None = None,
) -> DriveResult:
    """Localize every scan of a drive (see the module docstring).

    Args:
        triplet_map: the described map (:func:`~jaxloc.m2loc.build_map`,
            :func:`jaxloc.io.load_triplet_map`).
        scans: the drive, oldest first: a :class:`ScanSource` (a
            :func:`jaxloc.io.open_lidar_recording` recording) or a list of scans, each
            ``(points (M, 3), labels (M,))`` or an object with ``.points`` and ``.labels``
            (scan frame, metres; class ids of the map's classes).
        odometry: (N, 4, 4) pose of each scan in a fixed odometry frame, used with
            ``accumulate > 1`` or ``track`` (None: the source's own ``poses``, which must cover
            every scan).
        accumulate: K, the last scans fused into each query (1: each scan alone).
        track: step a :class:`~jaxloc.m2loc.Tracker` over the queries instead of localizing each
            globally.
        config: :class:`DriveConfig` (window growth, the window clique rule, tracking).
        query_config: the queries' settings (None: the map's; :func:`~jaxloc.m2loc.with_config`).
        progress: called after each scan with its index and :class:`DriveStep`.

    Returns:
        A :class:`DriveResult`.

    Raises:
        ValueError: bad settings (a ``query_config`` whose descriptor settings differ from the
            map's), odometry missing or of the wrong shape; a scan the source cannot
            read (its own error, naming the file); a query the pipeline refuses (duplicate
            points, unknown labels...: prefixed with the source's name of the scan).
    """
    config = DriveConfig() if config is None else config
    if query_config is not None:
        triplet_map = with_config(triplet_map, query_config)
    source = scans if isinstance(scans, ScanSource) else _ScanList(scans)
    count = len(source)
    least, most, min_instances = _window_sizes(accumulate, config)
    poses = _odometry(source, odometry, count) if least > 1 or track else None
    classes = triplet_map.config.descriptor.classes
    tracker = Tracker(triplet_map, config.track) if track else None
    state = tracker.init() if tracker is not None else None
    bands: set[int] = set()
    points, labels, steps = [], [], []
    for i in range(count):
        start = time.perf_counter()
        scan = source.instances(i, classes)
        load_ms = 1e3 * (time.perf_counter() - start)
        points.append(scan.points)
        labels.append(scan.labels)
        fused, small_clique = None, False
        try:
            if min(i + 1, most) > 1:
                fused = drive_window(
                    points, labels, poses, i, least, most, min_instances, config.merge_radius
                )
            query = scan if fused is None else ScanInstances(fused.points, fused.labels)
            if tracker is not None:
                T_prev_scan = np.linalg.inv(poses[i - 1]) @ poses[i] if i else np.eye(4)
                state, result, status, compile_s = _track(tracker, state, query, T_prev_scan, bands)
            else:
                result, compile_s = _localize(triplet_map, query, bands)
                if fused is not None:  # a window's pose must rest on more than the minimal set
                    small_clique = bool(result.valid) and result.clique_size < config.min_clique
                    result = require_clique(result, config.min_clique)
                status = RELOCALIZED if result.valid else LOST
        except ValueError as error:  # duplicate points and the like: a problem of the scan
            raise ValueError(f"{source.name(i)}: {error}") from error
        steps.append(DriveStep(result, status, scan, fused, small_clique, load_ms, compile_s))
        if progress is not None:
            progress(i, steps[-1])
    return DriveResult(
        poses=np.asarray([s.result.pose for s in steps], np.float64).reshape(-1, 4, 4),
        valid=np.array([bool(s.result.valid) for s in steps], bool),
        status=np.array([s.status for s in steps], np.int32),
        fused_scans=np.array([1 if s.fused is None else s.fused.members.shape[1] for s in steps]),
        load_ms=np.array([s.load_ms for s in steps], np.float64),
        localize_ms=np.array(
            [s.result.descriptor_time_ms + s.result.match_time_ms for s in steps], np.float64
        ),
        compile_s=np.array([s.compile_s for s in steps], np.float64),
        steps=tuple(steps),
    )
