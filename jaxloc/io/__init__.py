"""Real-world formats and map files, of both modalities: readers validate at the boundary and
raise ``FileNotFoundError`` or a ``ValueError`` (:class:`MapFormatError` for map files) naming the
file; writers write atomically (a temporary file, then a rename). Nothing is ever unpickled.

Camera (SG2Loc):

* :mod:`~jaxloc.io.camera_folder`: query sequences from a folder of RGB-D frames (ScanNet export).
* :mod:`~jaxloc.io.scannet`, :mod:`~jaxloc.io.rscan`, :mod:`~jaxloc.io.ply`: labelled
  reconstructions (ScanNet v2, 3RScan, any labelled PLY), as
  :class:`~jaxloc.io.reconstruction.LabelledReconstruction`.
* :mod:`~jaxloc.io.embedding_table`: object embeddings by label or object id.
* :mod:`~jaxloc.io.meshes`: a scene graph from mesh files and a text object list.
* :mod:`~jaxloc.io.scene_map`: the scene graph's own map file (:func:`save_scene`,
  :func:`load_scene`).

LiDAR (M2Loc):

* :mod:`~jaxloc.io.semantickitti`: SemanticKITTI scans (``.bin`` / ``.label``).
* :mod:`~jaxloc.io.lidar_sequence`: labelled scan sequences (SemanticKITTI layout, plain layout).
* :mod:`~jaxloc.io.instance_maps`: HeLiPR / TripletLoc instance maps and road normals (text).
* :mod:`~jaxloc.io.lidar_map`: the described M2Loc map's own file (:func:`save_triplet_map`,
  :func:`load_triplet_map`).
"""

from jaxloc.io.camera_folder import CameraFolder, load_camera_folder
from jaxloc.io.embedding_table import EmbeddingTable, load_embedding_table
from jaxloc.io.errors import MapFormatError
from jaxloc.io.instance_maps import (
    InstanceMap,
    load_instance_map,
    load_road_normals,
    save_lidar_maps,
)
from jaxloc.io.lidar_map import FORMAT_VERSION as TRIPLET_MAP_FORMAT_VERSION
from jaxloc.io.lidar_map import load_triplet_map, save_triplet_map
from jaxloc.io.lidar_sequence import (
    LidarSequence,
    is_sequence_dir,
    load_lidar_sequence,
    read_kitti_calibration,
    read_poses,
)
from jaxloc.io.meshes import load_meshes, load_objects_file, load_scene_from_files
from jaxloc.io.ply import read_generic
from jaxloc.io.reconstruction import LabelledReconstruction, ReconstructionObject
from jaxloc.io.rscan import read_3rscan
from jaxloc.io.scannet import read_label_table, read_scannet
from jaxloc.io.scene_map import load_scene, save_scene
from jaxloc.io.semantickitti import LabelledScan, load_semantickitti_scan, semantickitti_class_ids

__all__ = [
    "TRIPLET_MAP_FORMAT_VERSION",
    "CameraFolder",
    "EmbeddingTable",
    "InstanceMap",
    "LabelledReconstruction",
    "LabelledScan",
    "LidarSequence",
    "MapFormatError",
    "ReconstructionObject",
    "is_sequence_dir",
    "load_camera_folder",
    "load_embedding_table",
    "load_instance_map",
    "load_lidar_sequence",
    "load_meshes",
    "load_objects_file",
    "load_road_normals",
    "load_scene",
    "load_scene_from_files",
    "load_semantickitti_scan",
    "load_triplet_map",
    "read_3rscan",
    "read_generic",
    "read_kitti_calibration",
    "read_label_table",
    "read_poses",
    "read_scannet",
    "save_lidar_maps",
    "save_scene",
    "save_triplet_map",
    "semantickitti_class_ids",
]
