"""SG2Loc: sequential visual localization of a camera in a 3D scene graph with a particle filter.

Entry point: :func:`localize` (with :class:`SG2LocConfig`, returning :class:`SG2LocResult`), the
paper's coarse-to-fine rounds over a query :class:`Sequence`. The stages, one module each:

* :mod:`~jaxloc.sg2loc.sequence`: the query sequence (frames, camera, ego-motion, ground truth).
* :mod:`~jaxloc.sg2loc.rendering`: each particle's view of the map (ray casting into patches).
* :mod:`~jaxloc.sg2loc.particles`: the padded particle state, initialisation, motion model.
* :mod:`~jaxloc.sg2loc.scores`: semantic, depth and SSIM colour scores and the likelihood.
* :mod:`~jaxloc.sg2loc.resampling`: stratified / systematic resampling and KLD-sampling.
* :mod:`~jaxloc.sg2loc.filter`: one jitted filter step and passes over a sequence.
* :mod:`~jaxloc.sg2loc.verdict`: whether a frame is localized (computed inside the step).
* :mod:`~jaxloc.sg2loc.online`: the filter on a stream of frames (``init`` / ``update``).
* :mod:`~jaxloc.sg2loc.localization`: the coarse-to-fine rounds (:func:`localize`).
* :mod:`~jaxloc.sg2loc.refine`: Gauss-Newton / Levenberg-Marquardt 6-DoF pose refinement.
* :mod:`~jaxloc.sg2loc.learn`: learning the likelihood parameters by gradient.
* :mod:`~jaxloc.sg2loc.retrieval`: sequential scene retrieval in a database of scene graphs.
* :mod:`~jaxloc.sg2loc.sharded`: particles and passes split over several devices.
* :mod:`~jaxloc.sg2loc.figures`: the particles of every round over the map's floor plan.
"""

from typing import TYPE_CHECKING

from jaxloc._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, __file__)

if TYPE_CHECKING:  # the lazy names, for type checkers and the API reference
    from jaxloc.sg2loc import (
        filter,
        learn,
        online,
        particles,
        refine,
        resampling,
        retrieval,
        scores,
        sharded,
        verdict,
    )
    from jaxloc.sg2loc.localization import (
        SG2LocConfig,
        SG2LocResult,
        carry_back,
        localize,
        warm_up,
    )
    from jaxloc.sg2loc.rendering import Render, render, render_batch
    from jaxloc.sg2loc.sequence import Sequence

__all__ = [
    "Render",
    "SG2LocConfig",
    "SG2LocResult",
    "Sequence",
    "carry_back",
    "filter",
    "learn",
    "localize",
    "online",
    "particles",
    "refine",
    "render",
    "render_batch",
    "resampling",
    "retrieval",
    "scores",
    "sharded",
    "verdict",
    "warm_up",
]
