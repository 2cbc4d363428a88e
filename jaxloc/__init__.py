"""jaxloc: differentiable global localization against compact semantic maps, in JAX.

Two published methods as pure, jit/vmap-able functions:

* SG2Loc: sequential visual localization of a camera in a 3D scene graph (particle filter over
  ``(x, y, z, yaw)`` poses, BVH raycasting of coarse object meshes, semantic/depth/SSIM scores).
* M2Loc: one-shot LiDAR global localization from semantic instance centroids
  (:mod:`jaxloc.triplet`).
"""

from jaxloc import (
    filter,
    learn,
    lsq,
    metrics,
    particles,
    refine,
    resample,
    retrieval,
    scores,
    sg2loc,
    sharding,
    triplet,
)
from jaxloc._raycast import RayHit, raycast
from jaxloc._render import Render, render, render_batch
from jaxloc.camera import Camera, RayGrid, patch_grid, stride_grid
from jaxloc.scene import Capacity, MapFormatError, SceneGraph, load_scene, save_scene
from jaxloc.sequence import Sequence

__all__ = [
    "Camera",
    "Capacity",
    "MapFormatError",
    "RayGrid",
    "RayHit",
    "Render",
    "SceneGraph",
    "Sequence",
    "load_scene",
    "patch_grid",
    "raycast",
    "render",
    "render_batch",
    "save_scene",
    "stride_grid",
    "filter",
    "learn",
    "lsq",
    "metrics",
    "particles",
    "refine",
    "resample",
    "retrieval",
    "scores",
    "sg2loc",
    "sharding",
    "triplet",
]
