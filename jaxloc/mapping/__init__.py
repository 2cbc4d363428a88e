"""Map building: turning a user's recordings (read by :mod:`jaxloc.io`) into the methods' maps.

* :mod:`~jaxloc.mapping.scene_graphs`: SG2Loc scene graphs from labelled reconstructions (one
  coarse mesh per object, embeddings from a table or one-hot).
* :mod:`~jaxloc.mapping.lidar_maps`: M2Loc instance and road-surface-normal maps from a labelled
  LiDAR sequence (TripletLoc's recipe).

Both sit above :mod:`jaxloc.io` and the two method packages: they read with the former and build
the latter's types, so neither the readers nor the methods depend on each other.
"""

from typing import TYPE_CHECKING

from jaxloc._lazy import lazy_exports, public_names

__getattr__, __dir__ = lazy_exports(__name__, __file__)

if TYPE_CHECKING:  # the lazy names, for type checkers and the API reference
    from jaxloc.mapping.lidar_maps import (
        LidarMaps as LidarMaps,
        MapBuildConfig as MapBuildConfig,
        build_lidar_maps as build_lidar_maps,
        fit_plane as fit_plane,
    )
    from jaxloc.mapping.scene_graphs import (
        DEFAULT_TARGET_VERTICES as DEFAULT_TARGET_VERTICES,
        class_embeddings as class_embeddings,
        decimate as decimate,
        onehot_classes as onehot_classes,
        scene_graph_from_reconstruction as scene_graph_from_reconstruction,
    )

__all__ = public_names(__file__)
