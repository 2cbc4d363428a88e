"""M2Loc / TripletLoc one-shot global LiDAR localization from semantic instance centroids.

Pipeline: instances from labelled points (:func:`cluster_instances`) -> multi-scale triplet
descriptors (:func:`describe_points`, :func:`describe_map`) -> per-class top-k matching
(:func:`match_descriptors`) -> consistency graph (:func:`consistency_graph`) -> maximum clique
(:func:`max_clique`) with M2Loc's dynamic enhancement (and, for small scans, verified clique
hypotheses: :func:`best_verified_clique`) -> Kabsch + robust refinement with the
road-surface-normal prior (:func:`register`). User entry points: :func:`build_map` (saved
with :func:`save_triplet_map`, loaded with :func:`load_triplet_map`) and :func:`localize_scan`.
"""

from jaxloc.triplet._clique import (
    greedy_cliques,
    max_clique,
    max_clique_exact,
    max_clique_with_info,
    unpack_ranked,
)
from jaxloc.triplet._clusters import (
    ClusterConfig,
    Instances,
    cluster_instances,
    euclidean_clusters,
    fuse_instances,
    voxel_downsample,
)
from jaxloc.triplet._descriptors import (
    DescriptorConfig,
    class_positions,
    describe_map,
    describe_points,
    vertex_descriptor,
)
from jaxloc.triplet._hypotheses import (
    MapGrid,
    best_verified_clique,
    closed_form_poses,
    grid_verified_fraction,
    map_grid,
)
from jaxloc.triplet._io import (
    GRAPH_CLASSES,
    POLE,
    TRAFFIC_SIGN,
    TRUNK,
    InstanceMap,
    LabelledScan,
    RoadNormals,
    load_instance_map,
    load_road_normals,
    load_semantickitti_scan,
    semantickitti_class_ids,
)
from jaxloc.triplet._map_file import FORMAT_VERSION as TRIPLET_MAP_FORMAT_VERSION
from jaxloc.triplet._map_file import load_triplet_map, save_triplet_map
from jaxloc.triplet._mapping import (
    LidarMaps,
    MapBuildConfig,
    build_lidar_maps,
    fit_plane,
    save_lidar_maps,
)
from jaxloc.triplet._matching import consistency_graph, match_descriptors
from jaxloc.triplet._metrics import localization_errors, summarize_localization
from jaxloc.triplet._pipeline import (
    LocalizationResult,
    QueryOutput,
    TripletConfig,
    TripletMap,
    build_map,
    describe_query,
    localize_scan,
    m2loc_config,
    register_query,
    tripletloc_config,
    verified_fraction,
)
from jaxloc.triplet._registration import point_residuals, register, up_axis_prior, weighted_kabsch
from jaxloc.triplet._sequence import (
    LidarSequence,
    is_sequence_dir,
    load_lidar_sequence,
    read_kitti_calibration,
    read_poses,
)

__all__ = [
    "GRAPH_CLASSES",
    "POLE",
    "TRAFFIC_SIGN",
    "TRIPLET_MAP_FORMAT_VERSION",
    "TRUNK",
    "ClusterConfig",
    "DescriptorConfig",
    "InstanceMap",
    "Instances",
    "LabelledScan",
    "LidarMaps",
    "LidarSequence",
    "LocalizationResult",
    "MapGrid",
    "MapBuildConfig",
    "QueryOutput",
    "RoadNormals",
    "TripletConfig",
    "TripletMap",
    "best_verified_clique",
    "build_lidar_maps",
    "build_map",
    "class_positions",
    "closed_form_poses",
    "cluster_instances",
    "consistency_graph",
    "describe_map",
    "describe_points",
    "describe_query",
    "euclidean_clusters",
    "fit_plane",
    "fuse_instances",
    "greedy_cliques",
    "grid_verified_fraction",
    "is_sequence_dir",
    "load_instance_map",
    "load_lidar_sequence",
    "load_road_normals",
    "load_semantickitti_scan",
    "load_triplet_map",
    "localization_errors",
    "localize_scan",
    "m2loc_config",
    "map_grid",
    "match_descriptors",
    "max_clique",
    "max_clique_exact",
    "max_clique_with_info",
    "point_residuals",
    "read_kitti_calibration",
    "read_poses",
    "register",
    "register_query",
    "save_lidar_maps",
    "save_triplet_map",
    "semantickitti_class_ids",
    "summarize_localization",
    "tripletloc_config",
    "unpack_ranked",
    "up_axis_prior",
    "verified_fraction",
    "vertex_descriptor",
    "voxel_downsample",
    "weighted_kabsch",
]
