"""Recordings, map files and foreign formats, of both modalities. One naming rule:

* ``open_*`` a recording (a folder, a file of frames or scans) or a map of any kind it can be
  read from: :func:`open_camera_recording`, :func:`open_lidar_recording`,
  :func:`open_triplet_map`;
* ``load_*`` / ``save_*`` a jaxloc file (versioned ``.npz``, validated, never unpickled):
  :func:`load_scene` / :func:`save_scene`, :func:`load_triplet_map` / :func:`save_triplet_map`,
  :func:`load_class_embeddings`;
* ``read_*`` / ``write_*`` a foreign format (a dataset's files, text tables, pose files).

Readers validate at the boundary and raise ``FileNotFoundError`` or a ``ValueError``
(:class:`MapFormatError` for map files) naming the file; writers write atomically (a temporary
file, then a rename).

Camera (SG2Loc): recordings of ScanNet (export folders and ``.sens`` files), 3RScan and plain
folders (:func:`open_camera_recording`, poses out with :func:`write_camera_poses`); labelled
reconstructions (:func:`read_scannet`, :func:`read_3rscan`, :func:`read_labelled_ply`); a scene
graph's meshes and object list (:func:`read_mesh_scene`); object embeddings
(:func:`read_embedding_table`); patch embeddings from label images
(:func:`patch_embeddings_from_labels`).

LiDAR (M2Loc): recordings of SemanticKITTI, HeLiPR and plain layouts, scan files and centroid
files (:func:`open_lidar_recording`, poses out with :func:`write_lidar_poses`); single scans
(:func:`read_semantickitti_scan`, :func:`read_helipr_scan`, :func:`read_centroid_scan`); HeLiPR /
TripletLoc instance maps and road normals (:func:`read_instance_map`,
:func:`read_road_normals`, :func:`write_instance_maps`).

Recordings may also be ROS 1 ``.bag`` files, ROS 2 bag folders (sqlite3 or MCAP) or bare
``.mcap`` files (read with ``rosbags``, no ROS installation needed).

Poses: KITTI, 4x4-row and TUM files (:func:`read_pose_file`, :func:`write_tum`,
:func:`write_kitti`); poses for ROS tools (Foxglove, RViz) as ``geometry_msgs/PoseStamped`` in an
``.mcap`` file or a ROS 2 bag (:func:`write_pose_bag`).

A 3D view: :func:`write_rerun` (an SG2Loc run) and :func:`write_drive_rerun` (an M2Loc drive)
write Rerun recordings (``.rrd``; ``pip install "jaxloc[viz]"``).

The format modules (``jaxloc.io.scannet_sens``, ``jaxloc.io.lidar_sequence``, ...) hold the
lower-level readers these are built from.
"""

from typing import TYPE_CHECKING

from jaxloc._lazy import lazy_exports, public_names

__all__ = public_names(__file__)

if TYPE_CHECKING:  # where each public name comes from (jaxloc._lazy imports it on first use)
    from jaxloc.io.camera_recording import (
        open_camera_recording as open_camera_recording,
        write_camera_poses as write_camera_poses,
    )
    from jaxloc.io.camera_sequence import (
        CAMERA_FORMATS as CAMERA_FORMATS,
        CameraRecording as CameraRecording,
    )
    from jaxloc.io.embedding_table import (
        EmbeddingTable as EmbeddingTable,
        read_embedding_table as read_embedding_table,
    )
    from jaxloc.io.errors import (
        MapFormatError as MapFormatError,
    )
    from jaxloc.io.helipr import (
        read_helipr_scan as read_helipr_scan,
    )
    from jaxloc.io.instance_maps import (
        InstanceMap as InstanceMap,
        read_instance_map as read_instance_map,
        read_road_normals as read_road_normals,
        write_instance_maps as write_instance_maps,
    )
    from jaxloc.io.label_images import (
        patch_embeddings_from_labels as patch_embeddings_from_labels,
        read_label_image as read_label_image,
    )
    from jaxloc.io.lidar_map import (
        TRIPLET_MAP_FORMAT_VERSION as TRIPLET_MAP_FORMAT_VERSION,
        load_triplet_map as load_triplet_map,
        open_triplet_map as open_triplet_map,
        save_triplet_map as save_triplet_map,
    )
    from jaxloc.io.lidar_recording import (
        LidarRecording as LidarRecording,
        open_lidar_recording as open_lidar_recording,
        read_centroid_scan as read_centroid_scan,
        write_lidar_poses as write_lidar_poses,
    )
    from jaxloc.io.lidar_sequence import (
        LidarSequence as LidarSequence,
    )
    from jaxloc.io.meshes import (
        read_mesh_scene as read_mesh_scene,
        read_meshes as read_meshes,
        read_objects_file as read_objects_file,
    )
    from jaxloc.io.ply import (
        read_labelled_ply as read_labelled_ply,
    )
    from jaxloc.io.poses import (
        PoseFile as PoseFile,
        read_pose_file as read_pose_file,
        write_kitti as write_kitti,
        write_tum as write_tum,
    )
    from jaxloc.io.reconstruction import (
        LabelledReconstruction as LabelledReconstruction,
        ReconstructionObject as ReconstructionObject,
    )
    from jaxloc.io.rerun_log import (
        write_drive_rerun as write_drive_rerun,
        write_rerun as write_rerun,
    )
    from jaxloc.io.rosbag_poses import (
        write_pose_bag as write_pose_bag,
    )
    from jaxloc.io.rscan import (
        read_3rscan as read_3rscan,
    )
    from jaxloc.io.scannet import (
        read_label_table as read_label_table,
        read_scannet as read_scannet,
    )
    from jaxloc.io.scene_map import (
        ClassEmbeddings as ClassEmbeddings,
        load_class_embeddings as load_class_embeddings,
        load_scene as load_scene,
        save_scene as save_scene,
    )
    from jaxloc.io.semantickitti import (
        LabelledScan as LabelledScan,
        read_semantickitti_scan as read_semantickitti_scan,
    )

__getattr__, __dir__ = lazy_exports(
    __name__,
    __file__,
    # names of jaxloc 0.2 that moved to their format modules, or were renamed
    {
        "jaxloc.io.camera_recording": ("camera_pose_matrices",),
        "jaxloc.io.camera_sequence": (
            "detect_camera_format",
            "open_frame_source",
            "load_camera_sequence=read_camera_sequence",
        ),
        "jaxloc.io.embedding_table": ("load_embedding_table=read_embedding_table",),
        "jaxloc.io.helipr": ("load_helipr_scan=read_helipr_scan", "read_helipr_gt"),
        "jaxloc.io.instance_maps": (
            "load_instance_map=read_instance_map",
            "load_lidar_map=read_lidar_map",
            "load_road_normals=read_road_normals",
            "save_lidar_maps=write_instance_maps",
        ),
        "jaxloc.io.lidar_recording": ("load_centroid_scan=read_centroid_scan",),
        "jaxloc.io.lidar_sequence": (
            "detect_layout",
            "is_sequence_dir",
            "load_lidar_sequence=open_lidar_sequence",
            "load_sequence_scan=read_sequence_scan",
            "read_kitti_calibration",
        ),
        "jaxloc.io.meshes": (
            "load_meshes=read_meshes",
            "load_objects_file=read_objects_file",
            "load_scene_from_files=read_mesh_scene",
        ),
        "jaxloc.io.ply": ("read_generic=read_labelled_ply",),
        "jaxloc.io.poses": ("read_poses",),
        "jaxloc.io.rscan_sequence": ("open_rscan_sequence", "read_rescan_transform"),
        "jaxloc.io.scannet_export": ("open_scannet_export",),
        "jaxloc.io.scannet_sens": ("open_sens", "read_sens_header"),
        "jaxloc.io.semantickitti": (
            "load_semantickitti_scan=read_semantickitti_scan",
            "semantickitti_class_ids",
        ),
    },
    {
        "load_camera_sequence": "jaxloc.io.open_camera_recording",
        "load_lidar_sequence": "jaxloc.io.open_lidar_recording",
        "load_sequence_scan": "jaxloc.io.open_lidar_recording(...).scan(i)",
        "load_lidar_map": "jaxloc.io.read_instance_map and jaxloc.io.read_road_normals",
        "read_poses": "jaxloc.io.read_pose_file(path).poses",
        **{
            old: f"jaxloc.io.{new}"
            for old, new in {
                "load_embedding_table": "read_embedding_table",
                "load_helipr_scan": "read_helipr_scan",
                "load_instance_map": "read_instance_map",
                "load_road_normals": "read_road_normals",
                "save_lidar_maps": "write_instance_maps",
                "load_centroid_scan": "read_centroid_scan",
                "load_meshes": "read_meshes",
                "load_objects_file": "read_objects_file",
                "load_scene_from_files": "read_mesh_scene",
                "read_generic": "read_labelled_ply",
                "load_semantickitti_scan": "read_semantickitti_scan",
            }.items()
        },
    },
)
