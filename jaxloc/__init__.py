"""jaxloc: differentiable global localization against compact semantic maps, in JAX.

Two published methods as pure, jit/vmap-able functions:

* :mod:`jaxloc.sg2loc`: sequential visual localization of a camera in a 3D scene graph (particle
  filter over ``(x, y, z, yaw)`` poses, BVH ray casting of coarse object meshes, semantic, depth
  and SSIM scores).
* :mod:`jaxloc.m2loc`: one-shot global LiDAR localization from semantic instance centroids
  (M2Loc, and TripletLoc as a configuration).

Around them: the shared core at this level (:mod:`~jaxloc.scene`, :mod:`~jaxloc.camera`,
:mod:`~jaxloc.geometry`, :mod:`~jaxloc.lsq`, :mod:`~jaxloc.metrics`, :mod:`~jaxloc.sharding`,
:mod:`~jaxloc.figures`), :mod:`jaxloc.raycasting` (BVH, traversal, engines), :mod:`jaxloc.io`
(real formats and map files), :mod:`jaxloc.mapping` (maps from recordings),
:mod:`jaxloc.synthetic` (synthetic worlds) and :mod:`jaxloc.cli` (the ``jaxloc`` command).
"""

from importlib.metadata import PackageNotFoundError, version

from jaxloc import io, lsq, m2loc, mapping, metrics, raycasting, sg2loc, sharding
from jaxloc.camera import Camera, RayGrid, patch_grid, stride_grid
from jaxloc.io import MapFormatError, load_scene, save_scene
from jaxloc.raycasting import RayHit, raycast
from jaxloc.scene import Capacity, SceneGraph
from jaxloc.sg2loc import Render, Sequence, render, render_batch

try:
    __version__ = version("jaxloc")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

__all__ = [
    "Camera",
    "Capacity",
    "MapFormatError",
    "RayGrid",
    "RayHit",
    "Render",
    "SceneGraph",
    "Sequence",
    "__version__",
    "io",
    "load_scene",
    "lsq",
    "m2loc",
    "mapping",
    "metrics",
    "patch_grid",
    "raycast",
    "raycasting",
    "render",
    "render_batch",
    "save_scene",
    "sg2loc",
    "sharding",
    "stride_grid",
]
