"""M2Loc / TripletLoc: one-shot global LiDAR localization from semantic instance centroids.

Pipeline: instances from labelled points (:func:`cluster_instances`) -> multi-scale triplet
descriptors (:func:`describe_points`, :func:`describe_map`) -> per-class top-k matching
(:func:`match_descriptors`) -> consistency graph (:func:`consistency_graph`) -> maximum clique
(:func:`max_clique`) with M2Loc's dynamic enhancement (and, for small scans, verified clique
hypotheses: :func:`best_verified_clique`) -> Kabsch + robust refinement with the
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

from jaxloc.m2loc._accumulation import (
    MERGE_RADIUS,
    WINDOW_MIN_CLIQUE,
    WINDOW_MIN_INSTANCES,
    FusedScans,
    fuse_scans,
    grow_window,
    localize_window,
    require_clique,
)
from jaxloc.m2loc._batch import localize_scans
from jaxloc.m2loc._classes import GRAPH_CLASSES, POLE, TRAFFIC_SIGN, TRUNK
from jaxloc.m2loc._clique import (
    greedy_cliques,
    max_clique,
    max_clique_exact,
    max_clique_with_info,
    unpack_ranked,
)
from jaxloc.m2loc._clusters import (
    ClusterConfig,
    Instances,
    cluster_instances,
    euclidean_clusters,
    fuse_instances,
    voxel_downsample,
)
from jaxloc.m2loc._config import TripletConfig, m2loc_config, tripletloc_config
from jaxloc.m2loc._descriptors import (
    DescriptorConfig,
    class_positions,
    describe_map,
    describe_points,
    vertex_descriptor,
)
from jaxloc.m2loc._drive import (
    STATUS_NAMES,
    DriveConfig,
    DriveResult,
    DriveStep,
    ScanInstances,
    ScanSource,
    drive_window,
    localize_drive,
)
from jaxloc.m2loc._evaluation import (
    SUCCESS_RRE_DEG,
    SUCCESS_RTE_M,
    localization_errors,
    summarize_localization,
)
from jaxloc.m2loc._hypotheses import (
    MapGrid,
    best_verified_clique,
    closed_form_poses,
    grid_verified_fraction,
    host_map_grid,
    map_grid,
    verified_hypotheses,
)
from jaxloc.m2loc._localization import (
    LocalizationResult,
    PaddedScan,
    localize_scan,
    pad_scan,
    prepare_queries,
    query,
    query_capacity,
)
from jaxloc.m2loc._map import (
    SmallMapWarning,
    TripletMap,
    build_map,
    fit_config_to_map,
    triplet_map_spec,
    with_config,
)
from jaxloc.m2loc._matching import consistency_graph, match_descriptors
from jaxloc.m2loc._query import QueryOutput, describe_query, register_query, verified_fraction
from jaxloc.m2loc._registration import point_residuals, register, up_axis_prior, weighted_kabsch
from jaxloc.m2loc._road_normals import RoadNormals
from jaxloc.m2loc._tracking import (
    LOST,
    PENDING,
    RELOCALIZED,
    TRACKED,
    TrackConfig,
    Tracker,
    TrackResult,
    TrackState,
    grid_nearest_same_class,
    track_step,
)

__all__ = [
    "GRAPH_CLASSES",
    "LOST",
    "MERGE_RADIUS",
    "PENDING",
    "POLE",
    "RELOCALIZED",
    "STATUS_NAMES",
    "SUCCESS_RRE_DEG",
    "SUCCESS_RTE_M",
    "TRACKED",
    "TRAFFIC_SIGN",
    "TRUNK",
    "WINDOW_MIN_CLIQUE",
    "WINDOW_MIN_INSTANCES",
    "ClusterConfig",
    "DescriptorConfig",
    "DriveConfig",
    "DriveResult",
    "DriveStep",
    "FusedScans",
    "Instances",
    "LocalizationResult",
    "MapGrid",
    "QueryOutput",
    "RoadNormals",
    "ScanInstances",
    "ScanSource",
    "PaddedScan",
    "SmallMapWarning",
    "TrackConfig",
    "TrackResult",
    "TrackState",
    "Tracker",
    "TripletConfig",
    "TripletMap",
    "best_verified_clique",
    "build_map",
    "class_positions",
    "closed_form_poses",
    "cluster_instances",
    "consistency_graph",
    "describe_map",
    "describe_points",
    "describe_query",
    "drive_window",
    "euclidean_clusters",
    "fit_config_to_map",
    "fuse_instances",
    "fuse_scans",
    "grow_window",
    "greedy_cliques",
    "grid_nearest_same_class",
    "grid_verified_fraction",
    "host_map_grid",
    "localization_errors",
    "localize_drive",
    "localize_scan",
    "localize_scans",
    "localize_window",
    "m2loc_config",
    "map_grid",
    "match_descriptors",
    "pad_scan",
    "prepare_queries",
    "max_clique",
    "max_clique_exact",
    "max_clique_with_info",
    "point_residuals",
    "query",
    "query_capacity",
    "register",
    "register_query",
    "require_clique",
    "summarize_localization",
    "track_step",
    "triplet_map_spec",
    "tripletloc_config",
    "unpack_ranked",
    "up_axis_prior",
    "verified_fraction",
    "verified_hypotheses",
    "vertex_descriptor",
    "voxel_downsample",
    "weighted_kabsch",
    "with_config",
]
