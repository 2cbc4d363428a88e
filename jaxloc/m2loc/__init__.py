"""M2Loc / TripletLoc: one-shot global LiDAR localization from semantic instance centroids.

Pipeline: instances from labelled points (:func:`cluster_instances`) -> multi-scale triplet
descriptors (:func:`describe_points`, ``describe_map``) -> per-class top-k matching
(:func:`match_descriptors`) -> consistency graph (``consistency_graph``) -> maximum clique
(:func:`max_clique`) with M2Loc's dynamic enhancement (and, for small scans, verified clique
hypotheses: ``best_verified_clique``) -> Kabsch + robust refinement with the
road-surface-normal prior (:func:`register`). User entry points: :func:`build_map` and
:func:`localize_scan` (one scan; :func:`prepare_queries` compiles its programs ahead, in the
background), :func:`query` (the pure core: a padded scan, :func:`pad_scan`, in a map, under a
user's ``jit`` and ``vmap``; :func:`with_config` swaps a built map's query settings),
:func:`localize_scans` (a batch, on one device or split over several),
:func:`localize_window` (the fused instances of the last scans of a drive, :func:`fuse_scans`),
:class:`Tracker` (a drive tracked near the odometry prediction, global localization as fallback)
and :func:`localize_drive` (every scan of a drive or recording, alone, accumulated, tracked or
both, in one call). TripletLoc is one configuration away (:func:`tripletloc_config`). Map files
and the datasets' readers (recordings: :func:`jaxloc.io.open_lidar_recording`) live in
:mod:`jaxloc.io`; building instance maps from a labelled sequence in :mod:`jaxloc.mapping`.

Modules (private; everything public is re-exported here): ``_clusters`` (instances),
``_descriptors`` (triplet descriptors), ``_matching`` (matches, consistency graph), ``_clique``
(maximum clique solvers), ``_hypotheses`` (verified clique hypotheses), ``_registration`` (pose),
``_config`` / ``_map`` / ``_query`` / ``_localization`` / ``_batch`` (the pipeline),
``_accumulation`` (a window of scans fused through odometry), ``_tracking`` (tracking a drive),
``_drive`` (a whole drive: :func:`localize_drive`),
``_evaluation`` (errors and success rates), ``_classes`` and ``_road_normals`` (shared types).
"""

from jaxloc._lazy import deprecated_names, public_names
from jaxloc.m2loc._accumulation import (
    FusedScans as FusedScans,
    fuse_scans as fuse_scans,
    localize_window as localize_window,
)
from jaxloc.m2loc._batch import (
    localize_scans as localize_scans,
)
from jaxloc.m2loc._clique import (
    max_clique as max_clique,
)
from jaxloc.m2loc._clusters import (
    ClusterConfig as ClusterConfig,
    Instances as Instances,
    cluster_instances as cluster_instances,
)
from jaxloc.m2loc._config import (
    TripletConfig as TripletConfig,
    m2loc_config as m2loc_config,
    tripletloc_config as tripletloc_config,
)
from jaxloc.m2loc._descriptors import (
    DescriptorConfig as DescriptorConfig,
    describe_points as describe_points,
)
from jaxloc.m2loc._drive import (
    DriveConfig as DriveConfig,
    DriveResult as DriveResult,
    localize_drive as localize_drive,
)
from jaxloc.m2loc._evaluation import (
    localization_errors as localization_errors,
    summarize_localization as summarize_localization,
)
from jaxloc.m2loc._localization import (
    LocalizationResult as LocalizationResult,
    PaddedScan as PaddedScan,
    localize_scan as localize_scan,
    pad_scan as pad_scan,
    prepare_queries as prepare_queries,
    query as query,
)
from jaxloc.m2loc._map import (
    SmallMapWarning as SmallMapWarning,
    TripletMap as TripletMap,
    build_map as build_map,
    with_config as with_config,
)
from jaxloc.m2loc._matching import (
    match_descriptors as match_descriptors,
)
from jaxloc.m2loc._registration import (
    register as register,
)
from jaxloc.m2loc._road_normals import (
    RoadNormals as RoadNormals,
)
from jaxloc.m2loc._tracking import (
    TrackConfig as TrackConfig,
    Tracker as Tracker,
    TrackStatus as TrackStatus,
)

__all__ = public_names(__file__)

#: Names public in jaxloc 0.2 and internal now, or replaced: they still resolve, with a
#: DeprecationWarning, for one more release.
__getattr__ = deprecated_names(
    __name__,
    {
        "jaxloc.m2loc._accumulation": (
            "MERGE_RADIUS",
            "WINDOW_MIN_CLIQUE",
            "WINDOW_MIN_INSTANCES",
            "grow_window",
            "require_clique",
        ),
        "jaxloc.m2loc._classes": (
            "GRAPH_CLASSES",
            "POLE",
            "TRAFFIC_SIGN",
            "TRUNK",
        ),
        "jaxloc.m2loc._clique": (
            "greedy_cliques",
            "max_clique_exact",
            "max_clique_with_info",
            "unpack_ranked",
        ),
        "jaxloc.m2loc._clusters": (
            "euclidean_clusters",
            "fuse_instances",
            "voxel_downsample",
        ),
        "jaxloc.m2loc._descriptors": (
            "class_positions",
            "describe_map",
            "vertex_descriptor",
        ),
        "jaxloc.m2loc._drive": (
            "STATUS_NAMES",
            "DriveStep",
            "ScanInstances",
            "ScanSource",
            "drive_window",
        ),
        "jaxloc.m2loc._evaluation": (
            "SUCCESS_RRE_DEG",
            "SUCCESS_RTE_M",
        ),
        "jaxloc.m2loc._hypotheses": (
            "MapGrid",
            "best_verified_clique",
            "closed_form_poses",
            "grid_verified_fraction",
            "host_map_grid",
            "map_grid",
            "verified_hypotheses",
        ),
        "jaxloc.m2loc._localization": ("query_capacity",),
        "jaxloc.m2loc._map": (
            "fit_config_to_map",
            "triplet_map_spec",
        ),
        "jaxloc.m2loc._matching": ("consistency_graph",),
        "jaxloc.m2loc._query": (
            "QueryOutput",
            "describe_query",
            "register_query",
            "verified_fraction",
        ),
        "jaxloc.m2loc._registration": (
            "point_residuals",
            "up_axis_prior",
            "weighted_kabsch",
        ),
        "jaxloc.m2loc._tracking": (
            "LOST",
            "PENDING",
            "RELOCALIZED",
            "TRACKED",
            "TrackResult",
            "TrackState",
            "grid_nearest_same_class",
            "track_step",
        ),
    },
    {
        "STATUS_NAMES": "jaxloc.m2loc.TrackStatus(status).name",
        "LOST": "jaxloc.m2loc.TrackStatus.LOST",
        "PENDING": "jaxloc.m2loc.TrackStatus.PENDING",
        "RELOCALIZED": "jaxloc.m2loc.TrackStatus.RELOCALIZED",
        "TRACKED": "jaxloc.m2loc.TrackStatus.TRACKED",
        "track_step": "jaxloc.m2loc.Tracker",
        "TrackState": "jaxloc.m2loc.Tracker",
        "describe_map": "jaxloc.m2loc.build_map",
        "fit_config_to_map": "jaxloc.m2loc.build_map",
        "max_clique_exact": "jaxloc.m2loc.max_clique",
        "max_clique_with_info": "jaxloc.m2loc.max_clique",
        "describe_query": "jaxloc.m2loc.query",
        "register_query": "jaxloc.m2loc.query",
        "drive_window": "jaxloc.m2loc.localize_drive",
    },
)
