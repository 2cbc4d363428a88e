"""``jaxloc localize-lidar`` over a drive: the windows of ``--accumulate K`` (their sizes, the
odometry that fuses them) and the tracker of ``--track``."""

from __future__ import annotations

import argparse
import time

import numpy as np

from jaxloc.cli._errors import InputError
from jaxloc.cli._lidar_scans import ScanInstances, ScanRef, attach_ground_truth


def window_sizes(args: argparse.Namespace) -> tuple[int, int, int]:
    """``(K, M, N)`` of ``--accumulate K --accumulate-max M --window-instances N``, checked (and
    that ``--odometry`` is used), with their defaults (M = 2K, N =
    :data:`jaxloc.m2loc.WINDOW_MIN_INSTANCES`; (1, 1, 0) without ``--accumulate``)."""
    from jaxloc.m2loc import WINDOW_MIN_INSTANCES

    least, most, instances = args.accumulate, args.accumulate_max, args.window_instances
    if least < 1:
        raise InputError(f"--accumulate must be >= 1, got {least}")
    if args.odometry is not None and least == 1 and not args.track:
        raise InputError("--odometry is only used with --accumulate K > 1 or --track")
    if least == 1:
        for option, value in (("--window-instances", instances), ("--accumulate-max", most)):
            if value is not None:
                raise InputError(f"{option} is only used with --accumulate K > 1")
        return 1, 1, 0
    most = 2 * least if most is None else most
    instances = WINDOW_MIN_INSTANCES if instances is None else instances
    if most < least:
        raise InputError(f"--accumulate-max must be >= --accumulate ({least}), got {most}")
    if instances < 0:
        raise InputError(f"--window-instances must be >= 0, got {instances}")
    return least, most, instances


def window_odometry(refs: list[ScanRef], args: argparse.Namespace) -> np.ndarray | None:
    """(S, 4, 4) odometry poses of the scans for ``--accumulate K > 1`` or ``--track`` (else
    None): ``--odometry FILE`` (matched to the scans like ``--gt``), else the sequence's own
    poses."""
    if args.accumulate == 1 and not args.track:
        return None
    if args.odometry is not None:
        refs = attach_ground_truth(refs, args.odometry)
    missing = [ref.path.name for ref in refs if ref.T_gt is None]
    if missing:
        where = "--odometry" if args.odometry is not None else "the sequence's poses"
        raise InputError(
            f"--accumulate and --track need a pose for every scan; {where} has none for "
            f"{len(missing)} scan(s) (first: {missing[0]}); give --odometry FILE"
        )
    return np.stack([ref.T_gt for ref in refs])


def fuse_window(
    window: list[ScanInstances], poses: np.ndarray, least_scans: int, min_instances: int
) -> tuple[ScanInstances, int]:
    """The fused submap of the newest ``least_scans`` scans of ``window`` (newest first) in the
    newest scan's frame, grown with its older scans while it holds fewer than ``min_instances``
    instances (as :func:`jaxloc.m2loc.localize_window`), and how many scans it fused; ``poses``
    (K', 4, 4) odometry poses, newest first (at least as many as the window)."""
    from jaxloc.m2loc import grow_window

    newest = np.linalg.inv(poses[0])
    relative = np.stack([newest @ pose for pose in poses[: len(window)]])
    fused = grow_window(
        [s.points for s in window], [s.labels for s in window], relative, least_scans, min_instances
    )
    return ScanInstances(fused.points, fused.labels, 0.0), fused.members.shape[1]


#: The names of :data:`jaxloc.m2loc.TRACKED`, ``RELOCALIZED``, ``LOST`` and ``PENDING`` in the
#: records.
TRACK_MODES = ("tracked", "relocalized", "lost", "pending")


class DriveTracker:
    """``--track``: a :class:`jaxloc.m2loc.Tracker` stepped scan by scan (one compiled step per
    query size band; its first run in a band is run twice, the pure step from the same state, to
    time the step alone)."""

    def __init__(self, triplet_map):
        from jaxloc.m2loc import Tracker

        self.tracker = Tracker(triplet_map)
        self.state = self.tracker.init()
        self.bands: set[int] = set()

    def step(self, scan: ScanInstances, T_prev_scan: np.ndarray):
        """Returns a :class:`~jaxloc.m2loc.LocalizationResult` (``clique_size``: the local
        associations), the mode's name and the compile or load time (s)."""
        import jax

        from jaxloc.m2loc import LocalizationResult, pad_scan, query_capacity, track_step

        config = self.tracker.triplet_map.config
        band = query_capacity(max(len(scan.points), 1), config)
        padded = pad_scan(scan.points, scan.labels, config, band)

        def run():
            start = time.perf_counter()
            out = jax.block_until_ready(track_step(self.tracker, self.state, padded, T_prev_scan))
            return out, time.perf_counter() - start

        (state, out), seconds = run()
        compile_s = 0.0
        if band not in self.bands:
            self.bands.add(band)
            (state, out), again = run()
            compile_s, seconds = max(seconds - again, 0.0), again
        self.state = state
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
        return result, TRACK_MODES[int(out.mode)], compile_s
