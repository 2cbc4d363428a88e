"""SG2Loc: sequential visual localization of a camera in a 3D scene graph with a particle filter.

Entry point: :func:`localize` (with :class:`SG2LocConfig`, returning :class:`SG2LocResult`), the
paper's coarse-to-fine rounds over a query :class:`FrameSequence`; :func:`warm_up` compiles its
programs ahead. The same configuration drives the streaming filter (:mod:`~jaxloc.sg2loc.online`:
``init`` / ``update``, one frame at a time).

One filter step, BlackJAX-style: :func:`step` ``(key, state, frame, scene, config) -> (state,
info)`` on a :class:`ParticleState`, a :class:`Frame` and a :class:`StepConfig` (one round's
configuration, which :func:`localize` and the streaming filter derive from their
:class:`SG2LocConfig`), and :func:`run_pass` (a ``lax.scan`` of it over the frames). What each
particle sees: :func:`render`, :func:`render_batch`. The scores' settings:
:class:`ObservationConfig` (and :func:`check_ssim_strides`, whether a stride leaves the colour
score enough rays); KLD-sampling: :class:`KLDConfig` (:func:`kld_for_capacity`, the bounds for a
particle capacity); the per-frame verdict: :class:`VerdictConfig`, :class:`Verdict` (its calibrated
:class:`ConfidenceModel`); a check of estimates chosen without the depth:
:func:`depth_agreement` (:class:`AgreementConfig`), and the check built on it,
:func:`depth_blind_check` (:class:`DepthCheck`): a depth-blind filter's estimates measured
against the recording's depth.

Around them: :mod:`~jaxloc.sg2loc.refine` (6-DoF pose refinement), :mod:`~jaxloc.sg2loc.learn`
(learning the likelihood parameters), :mod:`~jaxloc.sg2loc.retrieval` (scene retrieval),
:mod:`~jaxloc.sg2loc.sharded` (particles split over devices) and :mod:`~jaxloc.sg2loc.figures`.
The stages live in private modules (``_sequence``, ``_rendering``, ``_particles``, ``_scores``,
``_resampling``, ``_verdict``, ``_agreement``, ``_check``, ``_filter``, ``_rounds``,
``_localization``).
"""

from typing import TYPE_CHECKING

from jaxloc._lazy import lazy_exports, public_names, renamed_modules

__all__ = public_names(__file__)

if TYPE_CHECKING:  # where each public name comes from (jaxloc._lazy imports it on first use)
    from jaxloc.sg2loc import (
        figures as figures,
        learn as learn,
        online as online,
        refine as refine,
        retrieval as retrieval,
        sharded as sharded,
    )
    from jaxloc.sg2loc._agreement import (
        AgreementConfig as AgreementConfig,
        depth_agreement as depth_agreement,
    )
    from jaxloc.sg2loc._check import (
        DepthCheck as DepthCheck,
        depth_blind_check as depth_blind_check,
    )
    from jaxloc.sg2loc._filter import (
        Region as Region,
        StepConfig as StepConfig,
        StepInfo as StepInfo,
        run_pass as run_pass,
        step as step,
    )
    from jaxloc.sg2loc._localization import (
        SG2LocConfig as SG2LocConfig,
        SG2LocResult as SG2LocResult,
        localize as localize,
        warm_up as warm_up,
    )
    from jaxloc.sg2loc._particles import (
        PAPER_HEIGHTS as PAPER_HEIGHTS,
        ParticleState as ParticleState,
    )
    from jaxloc.sg2loc._rendering import (
        Render as Render,
        render as render,
        render_batch as render_batch,
    )
    from jaxloc.sg2loc._resampling import (
        KLDConfig as KLDConfig,
        kld_for_capacity as kld_for_capacity,
    )
    from jaxloc.sg2loc._rounds import (
        carry_back as carry_back,
    )
    from jaxloc.sg2loc._scores import (
        ObservationConfig as ObservationConfig,
        check_ssim_strides as check_ssim_strides,
    )
    from jaxloc.sg2loc._sequence import (
        Frame as Frame,
        FrameSequence as FrameSequence,
        frames_on_grid as frames_on_grid,
    )
    from jaxloc.sg2loc._verdict import (
        ConfidenceModel as ConfidenceModel,
        Verdict as Verdict,
        VerdictConfig as VerdictConfig,
        default_verdict as default_verdict,
    )

#: The stage modules of jaxloc 0.2, private now: ``import jaxloc.sg2loc.filter`` and
#: ``jaxloc.sg2loc.filter`` still work, with a DeprecationWarning, for one more release.
_RENAMED_MODULES = {
    name: f"_{name}"
    for name in (
        "filter",
        "localization",
        "particles",
        "rendering",
        "resampling",
        "scores",
        "sequence",
        "verdict",
    )
}
renamed_modules(__name__, _RENAMED_MODULES)
__getattr__, __dir__ = lazy_exports(
    __name__,
    __file__,
    {
        __name__: [f"{old}={new}" for old, new in _RENAMED_MODULES.items()],
        "jaxloc.sg2loc._sequence": ("Sequence=FrameSequence",),
    },
    {"Sequence": "jaxloc.sg2loc.FrameSequence"},
)
