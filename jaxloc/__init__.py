"""jaxloc: differentiable global localization against compact semantic maps, in JAX.

Two published methods as pure, jit/vmap-able functions:

* :mod:`jaxloc.sg2loc`: sequential visual localization of a camera in a 3D scene graph (particle
  filter over ``(x, y, z, yaw)`` poses, BVH ray casting of coarse object meshes, semantic, depth
  and SSIM scores).
* :mod:`jaxloc.m2loc`: one-shot global LiDAR localization from semantic instance centroids
  (M2Loc, and TripletLoc as a configuration).

Around them: the shared core at this level (:mod:`~jaxloc.scene`, :mod:`~jaxloc.camera`,
:mod:`~jaxloc.geometry`, :mod:`~jaxloc.lsq`, :mod:`~jaxloc.metrics`, :mod:`~jaxloc.sharding`,
:mod:`~jaxloc.figures`, :mod:`~jaxloc.compilation_cache`), :mod:`jaxloc.raycasting` (BVH,
traversal, engines), :mod:`jaxloc.io` (real formats and map files), :mod:`jaxloc.mapping` (maps
from recordings), :mod:`jaxloc.synthetic` (synthetic worlds) and :mod:`jaxloc.cli` (the ``jaxloc``
command).

``import jaxloc`` is cheap: the names below and the subpackages are imported on first use (so
``jaxloc --help`` never imports JAX).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING

from jaxloc._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(
    __name__,
    __file__,
    {"jaxloc.sg2loc._sequence": ("Sequence=FrameSequence",)},  # the name of jaxloc 0.2
    {"Sequence": "jaxloc.FrameSequence"},
)

try:
    __version__ = version("jaxloc")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

__all__ = [
    "__version__",
    "Camera",
    "Capacity",
    "MapFormatError",
    "RayGrid",
    "RayHit",
    "Render",
    "SceneGraph",
    "FrameSequence",
    "enable_compilation_cache",
    "load_scene",
    "patch_grid",
    "raycast",
    "render",
    "render_batch",
    "save_scene",
    "stride_grid",
    "camera",
    "compilation_cache",
    "figures",
    "geometry",
    "io",
    "lsq",
    "m2loc",
    "mapping",
    "metrics",
    "raycasting",
    "scene",
    "sg2loc",
    "sharding",
    "synthetic",
]


if TYPE_CHECKING:  # what the lazy names are, for type checkers and the docs
    from jaxloc import (
        camera,
        compilation_cache,
        figures,
        geometry,
        io,
        lsq,
        m2loc,
        mapping,
        metrics,
        raycasting,
        scene,
        sg2loc,
        sharding,
        synthetic,
    )
    from jaxloc.camera import Camera, RayGrid, patch_grid, stride_grid
    from jaxloc.compilation_cache import enable_compilation_cache
    from jaxloc.io.errors import MapFormatError
    from jaxloc.io.scene_map import load_scene, save_scene
    from jaxloc.raycasting.hits import RayHit, raycast
    from jaxloc.scene import Capacity, SceneGraph
    from jaxloc.sg2loc._rendering import Render, render, render_batch
    from jaxloc.sg2loc._sequence import FrameSequence
