"""Real-world formats and map files, of both modalities: readers validate at the boundary and
raise ``FileNotFoundError`` or a ``ValueError`` (:class:`MapFormatError` for map files) naming the
file; writers write atomically (a temporary file, then a rename). Nothing is ever unpickled.

Camera (SG2Loc):

* :mod:`~jaxloc.io.camera_recording`: a camera recording opened as a query in one call
  (:func:`open_camera_recording`), its estimated poses written for evo
  (:func:`write_camera_poses`).
* :mod:`~jaxloc.io.camera_sequence`: query sequences from camera recordings, in any of
  :mod:`~jaxloc.io.scannet_export` (ScanNet's export folder), :mod:`~jaxloc.io.scannet_sens`
  (ScanNet ``.sens`` files) and :mod:`~jaxloc.io.rscan_sequence` (3RScan sequences), their frames
  as :mod:`~jaxloc.io.camera_frames` defines them; patch embeddings from label images
  (:mod:`~jaxloc.io.label_images`).
* :mod:`~jaxloc.io.scannet`, :mod:`~jaxloc.io.rscan`, :mod:`~jaxloc.io.ply`: labelled
  reconstructions (ScanNet v2, 3RScan, any labelled PLY), as
  :class:`~jaxloc.io.reconstruction.LabelledReconstruction`.
* :mod:`~jaxloc.io.embedding_table`: object embeddings by label or object id.
* :mod:`~jaxloc.io.meshes`: a scene graph from mesh files and a text object list.
* :mod:`~jaxloc.io.scene_map`: the scene graph's own map file (:func:`save_scene`,
  :func:`load_scene`, and the map's class embeddings).

LiDAR (M2Loc):

* :mod:`~jaxloc.io.semantickitti`: SemanticKITTI scans (``.bin`` / ``.label``).
* :mod:`~jaxloc.io.lidar_sequence`: labelled scan sequences (SemanticKITTI, plain and HeLiPR
  layouts), each scan read by :func:`load_sequence_scan`.
* :mod:`~jaxloc.io.lidar_recording`: any LiDAR recording jaxloc reads (a sequence folder of any
  layout, scan files, centroid files) as one :class:`LidarRecording`
  (:func:`open_lidar_recording`), and estimated poses written for evo
  (:func:`write_lidar_poses`).
* :mod:`~jaxloc.io.helipr`: HeLiPR / TripletLoc scans (four sensors' point records), SPVNAS
  labels and ground truth.
* :mod:`~jaxloc.io.poses`: pose files (KITTI, 4x4 rows, TUM) in and out (:func:`read_pose_file`,
  :func:`write_tum`, :func:`write_kitti`).
* :mod:`~jaxloc.io.instance_maps`: HeLiPR / TripletLoc instance maps and road normals (text).
* :mod:`~jaxloc.io.lidar_map`: the described M2Loc map's own file (:func:`save_triplet_map`,
  :func:`load_triplet_map`), and the described map of a file or folder (:func:`open_triplet_map`).
"""

from typing import TYPE_CHECKING

from jaxloc._lazy import lazy_exports

#: Public name -> the submodule that defines it (imported on first use: importing the package
#: costs only what is used).
_EXPORTS = {
    "CAMERA_FORMATS": "camera_sequence",
    "CameraRecording": "camera_sequence",
    "detect_camera_format": "camera_sequence",
    "load_camera_sequence": "camera_sequence",
    "open_frame_source": "camera_sequence",
    "camera_pose_matrices": "camera_recording",
    "open_camera_recording": "camera_recording",
    "write_camera_poses": "camera_recording",
    "EmbeddingTable": "embedding_table",
    "load_embedding_table": "embedding_table",
    "MapFormatError": "errors",
    "load_helipr_scan": "helipr",
    "read_helipr_gt": "helipr",
    "InstanceMap": "instance_maps",
    "load_instance_map": "instance_maps",
    "load_lidar_map": "instance_maps",
    "load_road_normals": "instance_maps",
    "save_lidar_maps": "instance_maps",
    "patch_embeddings_from_labels": "label_images",
    "read_label_image": "label_images",
    "TRIPLET_MAP_FORMAT_VERSION": "lidar_map:FORMAT_VERSION",
    "load_triplet_map": "lidar_map",
    "open_triplet_map": "lidar_map",
    "save_triplet_map": "lidar_map",
    "LidarRecording": "lidar_recording",
    "load_centroid_scan": "lidar_recording",
    "open_lidar_recording": "lidar_recording",
    "write_lidar_poses": "lidar_recording",
    "LidarSequence": "lidar_sequence",
    "detect_layout": "lidar_sequence",
    "is_sequence_dir": "lidar_sequence",
    "load_lidar_sequence": "lidar_sequence",
    "load_sequence_scan": "lidar_sequence",
    "read_kitti_calibration": "lidar_sequence",
    "load_meshes": "meshes",
    "load_objects_file": "meshes",
    "load_scene_from_files": "meshes",
    "read_generic": "ply",
    "PoseFile": "poses",
    "read_pose_file": "poses",
    "read_poses": "poses",
    "write_kitti": "poses",
    "write_tum": "poses",
    "LabelledReconstruction": "reconstruction",
    "ReconstructionObject": "reconstruction",
    "read_3rscan": "rscan",
    "open_rscan_sequence": "rscan_sequence",
    "read_rescan_transform": "rscan_sequence",
    "read_label_table": "scannet",
    "read_scannet": "scannet",
    "open_scannet_export": "scannet_export",
    "open_sens": "scannet_sens",
    "read_sens_header": "scannet_sens",
    "ClassEmbeddings": "scene_map",
    "load_class_embeddings": "scene_map",
    "load_scene": "scene_map",
    "save_scene": "scene_map",
    "LabelledScan": "semantickitti",
    "load_semantickitti_scan": "semantickitti",
    "semantickitti_class_ids": "semantickitti",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # the lazy names, for type checkers and the API reference
    from jaxloc.io.camera_recording import (
        camera_pose_matrices,
        open_camera_recording,
        write_camera_poses,
    )
    from jaxloc.io.camera_sequence import (
        CAMERA_FORMATS,
        CameraRecording,
        detect_camera_format,
        load_camera_sequence,
        open_frame_source,
    )
    from jaxloc.io.embedding_table import EmbeddingTable, load_embedding_table
    from jaxloc.io.errors import MapFormatError
    from jaxloc.io.helipr import load_helipr_scan, read_helipr_gt
    from jaxloc.io.instance_maps import (
        InstanceMap,
        load_instance_map,
        load_lidar_map,
        load_road_normals,
        save_lidar_maps,
    )
    from jaxloc.io.label_images import patch_embeddings_from_labels, read_label_image
    from jaxloc.io.lidar_map import FORMAT_VERSION as TRIPLET_MAP_FORMAT_VERSION
    from jaxloc.io.lidar_map import load_triplet_map, open_triplet_map, save_triplet_map
    from jaxloc.io.lidar_recording import (
        LidarRecording,
        load_centroid_scan,
        open_lidar_recording,
        write_lidar_poses,
    )
    from jaxloc.io.lidar_sequence import (
        LidarSequence,
        detect_layout,
        is_sequence_dir,
        load_lidar_sequence,
        load_sequence_scan,
        read_kitti_calibration,
    )
    from jaxloc.io.meshes import load_meshes, load_objects_file, load_scene_from_files
    from jaxloc.io.ply import read_generic
    from jaxloc.io.poses import PoseFile, read_pose_file, read_poses, write_kitti, write_tum
    from jaxloc.io.reconstruction import LabelledReconstruction, ReconstructionObject
    from jaxloc.io.rscan import read_3rscan
    from jaxloc.io.rscan_sequence import open_rscan_sequence, read_rescan_transform
    from jaxloc.io.scannet import read_label_table, read_scannet
    from jaxloc.io.scannet_export import open_scannet_export
    from jaxloc.io.scannet_sens import open_sens, read_sens_header
    from jaxloc.io.scene_map import ClassEmbeddings, load_class_embeddings, load_scene, save_scene
    from jaxloc.io.semantickitti import (
        LabelledScan,
        load_semantickitti_scan,
        semantickitti_class_ids,
    )

__all__ = [
    "TRIPLET_MAP_FORMAT_VERSION",
    "CAMERA_FORMATS",
    "CameraRecording",
    "ClassEmbeddings",
    "EmbeddingTable",
    "InstanceMap",
    "LabelledReconstruction",
    "LabelledScan",
    "LidarRecording",
    "LidarSequence",
    "PoseFile",
    "MapFormatError",
    "ReconstructionObject",
    "detect_layout",
    "is_sequence_dir",
    "camera_pose_matrices",
    "detect_camera_format",
    "load_camera_sequence",
    "load_centroid_scan",
    "load_class_embeddings",
    "open_camera_recording",
    "open_frame_source",
    "open_lidar_recording",
    "open_triplet_map",
    "open_rscan_sequence",
    "open_scannet_export",
    "open_sens",
    "patch_embeddings_from_labels",
    "read_label_image",
    "read_rescan_transform",
    "read_sens_header",
    "load_embedding_table",
    "load_instance_map",
    "load_lidar_map",
    "load_helipr_scan",
    "load_lidar_sequence",
    "load_sequence_scan",
    "load_meshes",
    "load_objects_file",
    "load_road_normals",
    "load_scene",
    "load_scene_from_files",
    "load_semantickitti_scan",
    "load_triplet_map",
    "read_3rscan",
    "read_generic",
    "read_helipr_gt",
    "read_kitti_calibration",
    "read_label_table",
    "read_pose_file",
    "read_poses",
    "read_scannet",
    "save_lidar_maps",
    "save_scene",
    "save_triplet_map",
    "semantickitti_class_ids",
    "write_camera_poses",
    "write_kitti",
    "write_lidar_poses",
    "write_tum",
]
