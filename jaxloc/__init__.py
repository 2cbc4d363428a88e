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

from jaxloc._lazy import lazy_exports, public_names

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

__all__ = ["__version__", *public_names(__file__)]


if TYPE_CHECKING:  # what the lazy names are, for type checkers and the docs
    from jaxloc import (
        camera as camera,
        compilation_cache as compilation_cache,
        figures as figures,
        geometry as geometry,
        io as io,
        lsq as lsq,
        m2loc as m2loc,
        mapping as mapping,
        metrics as metrics,
        raycasting as raycasting,
        scene as scene,
        sg2loc as sg2loc,
        sharding as sharding,
        synthetic as synthetic,
    )
    from jaxloc.camera import (
        Camera as Camera,
        RayGrid as RayGrid,
        patch_grid as patch_grid,
        stride_grid as stride_grid,
    )
    from jaxloc.compilation_cache import (
        enable_compilation_cache as enable_compilation_cache,
    )
    from jaxloc.io.errors import (
        MapFormatError as MapFormatError,
    )
    from jaxloc.io.scene_map import (
        load_scene as load_scene,
        save_scene as save_scene,
    )
    from jaxloc.raycasting.hits import (
        RayHit as RayHit,
        raycast as raycast,
    )
    from jaxloc.scene import (
        Capacity as Capacity,
        SceneGraph as SceneGraph,
    )
    from jaxloc.sg2loc._rendering import (
        Render as Render,
        render as render,
        render_batch as render_batch,
    )
    from jaxloc.sg2loc._sequence import (
        FrameSequence as FrameSequence,
    )
