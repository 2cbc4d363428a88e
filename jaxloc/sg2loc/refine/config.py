"""Configuration, observations and result of the pose refinement (status codes: the package
docstring of :mod:`jaxloc.sg2loc.refine`)."""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jaxlie
from jax import Array

from jaxloc.lsq import RobustLoss
from jaxloc.raycasting.engines import check_engine_name

#: The residuals of a refinement (``RefineConfig.residuals``): depth (a), reprojection (b), both.
ResidualKind = Literal["depth", "reprojection", "both"]
#: The frames a refinement uses (``RefineConfig.mode``): the last one or the whole sequence.
Mode = Literal["last", "sequence"]

#: ``RefineResult.status``: converged (the result is ok).
STATUS_CONVERGED = 0
#: ``RefineResult.status``: not converged (step budget spent or a non-finite iterate).
STATUS_NOT_CONVERGED = 1
#: ``RefineResult.status``: non-finite or empty input.
STATUS_BAD_INPUT = 2
#: ``RefineResult.status``: too few valid residuals at the initial pose.
STATUS_TOO_FEW_RESIDUALS = 3
#: ``RefineResult.status``: moved farther than ``max_translation`` / ``max_rotation``.
STATUS_DIVERGED = 4
#: ``RefineResult.status``: the data leave the pose undetermined along some direction.
STATUS_DEGENERATE = 5
#: ``RefineResult.status``: the solved pose explains too few of the observations.
STATUS_POOR_FIT = 6

#: Rounds end after one that moves the pose < this (metres) and turns it < SETTLED_ROTATION.
SETTLED_TRANSLATION = 1e-4
#: Rounds end after one that turns the pose < this (radians) and moves it < SETTLED_TRANSLATION.
SETTLED_ROTATION = 1e-4


class RefineConfig(eqx.Module):
    """Settings of the refinement. Kinds, sizes and step budgets are static; the rest is traced.

    Attributes:
        residuals: "depth" (a), "reprojection" (b) or "both" (c) (static).
        mode: "last" (refine the last frame alone) or "sequence" (all frames jointly through the
            ego-motion, one SE(3) anchor) (static).
        depth_stride: every ``depth_stride``-th pixel of the depth image is used (static).
        depth_sigma_abs, depth_sigma_rel: depth noise ``abs + rel * depth`` (metres, fraction)
            that normalises the depth residuals.
        pixel_sigma: reprojection noise (pixels) that normalises the reprojection residuals.
        loss: robust loss on the normalised residual blocks (scale in units of sigma).
        min_incidence: depth pixels whose ray meets the hit plane with ``|cos| < min_incidence``
            (grazing) are dropped.
        search_radius, search_spacing: association window of the depth pixels in candidate rays
            (static) and pixels between them (:func:`associate_depth`; 0 = projective).
        min_depth: correspondences less than this far in front of the camera (metres) are dropped.
        min_depth_pixels, min_matches: fewest valid depth pixels / correspondences (over all frames,
            at the initial pose) for that residual type to count; with neither enough the result is
            status 3 (static).
        max_translation, max_rotation: a solve that moves the pose farther than this (metres,
            radians) is reported as diverged (status 4).
        max_position_std, max_rotation_std: a converged solve whose 1-sigma pose uncertainty
            along its worst direction exceeds this (metres, radians; :mod:`jaxloc.sg2loc.refine`) is
            reported as degenerate (status 5).
        inlier_threshold: a residual block is an inlier of the final pose when its norm is at
            most this (in units of sigma).
        min_inlier_fraction: a converged, determined solve whose final pose explains less than
            this fraction of the valid residuals (depth re-associated at the final pose) is
            reported as a poor fit (status 6); 0 disables the check (:mod:`jaxloc.sg2loc.refine`).
        rounds: the most data-association rounds of the depth residuals (projective ICP;
            static); each restarts the solver from the last iterate, and once a round moves the
            pose less than 0.1 mm and 0.1 mrad the remaining rounds are skipped. 16 by default: in
            the noise-free sweep (experiments/results/refine/convergence.md) joint depth
            refinement of a sequence was still moving after 8 rounds on 2 of 12 starts (0.31 m
            off) and converged with 16. Reprojection-only refinement needs no
            association and runs one round of ``rounds * max_steps`` steps (the same budget):
            restarting Levenberg-Marquardt every ``max_steps`` resets its damping, and with the
            Huber loss far outside its scale it needs more than 20 consecutive steps (measured:
            8 rounds x 20 steps left the same starts unconverged as 1 x 20;
            experiments/results/refine/convergence.md).
        max_steps: optimiser steps per round (static).
        method: "lm" (Levenberg-Marquardt) or "gn" (Gauss-Newton) (static).
        engine: nearest-hit engine of the depth association (static; see
            :func:`jaxloc.raycast`).
    """

    residuals: ResidualKind = eqx.field(static=True, default="depth")
    mode: Mode = eqx.field(static=True, default="last")
    depth_stride: int = eqx.field(static=True, default=4)
    depth_sigma_abs: float = 0.01
    depth_sigma_rel: float = 0.02
    pixel_sigma: float = 1.0
    loss: RobustLoss = RobustLoss("huber", 2.0)
    min_incidence: float = 0.1
    search_radius: int = eqx.field(static=True, default=2)
    search_spacing: float = 4.0
    min_depth: float = 0.05
    min_depth_pixels: int = eqx.field(static=True, default=12)
    min_matches: int = eqx.field(static=True, default=4)
    max_translation: float = 1.0
    max_rotation: float = 0.6
    max_position_std: float = 0.05
    max_rotation_std: float = 0.02
    inlier_threshold: float = 3.0
    min_inlier_fraction: float = 0.0
    rounds: int = eqx.field(static=True, default=16)
    max_steps: int = eqx.field(static=True, default=20)
    method: Literal["lm", "gn"] = eqx.field(static=True, default="lm")
    engine: str = eqx.field(static=True, default="auto")

    def __check_init__(self) -> None:
        check_engine_name(self.engine)
        if self.residuals not in ("depth", "reprojection", "both"):
            raise ValueError(
                f"residuals must be 'depth', 'reprojection' or 'both', got {self.residuals!r}"
            )
        if self.mode not in ("last", "sequence"):
            raise ValueError(f"mode must be 'last' or 'sequence', got {self.mode!r}")
        if not isinstance(self.rounds, int) or self.rounds < 1:
            raise ValueError(f"rounds must be a positive int, got {self.rounds!r}")
        if not isinstance(self.depth_stride, int) or self.depth_stride < 1:
            raise ValueError(f"depth_stride must be a positive int, got {self.depth_stride!r}")
        if self.method not in ("lm", "gn"):
            raise ValueError(f"method must be 'lm' or 'gn', got {self.method!r}")
        for name in (
            "pixel_sigma",
            "max_translation",
            "max_rotation",
            "max_position_std",
            "max_rotation_std",
            "inlier_threshold",
        ):
            value = getattr(self, name)
            if isinstance(value, float | int) and not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        for name in ("depth_sigma_abs", "depth_sigma_rel"):
            value = getattr(self, name)
            if isinstance(value, float | int) and not value >= 0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        abs_, rel = self.depth_sigma_abs, self.depth_sigma_rel
        if isinstance(abs_, float | int) and isinstance(rel, float | int) and abs_ + rel <= 0:
            raise ValueError("depth_sigma_abs + depth_sigma_rel must be > 0")
        fraction = self.min_inlier_fraction
        if isinstance(fraction, float | int) and not 0.0 <= fraction <= 1.0:
            raise ValueError(f"min_inlier_fraction must be in [0, 1], got {fraction}")

    @property
    def uses_depth(self) -> bool:
        return self.residuals in ("depth", "both")

    @property
    def uses_matches(self) -> bool:
        return self.residuals in ("reprojection", "both")


class Observations(eqx.Module):
    """What the refinement compares against, for F frames (F = 1 in ``mode="last"``).

    Attributes:
        depth_uv: (N, 2) float32 pixel coordinates of the depth samples (shared by all frames).
        depth: (F, N) float32 depth along the optical axis (metres); 0 or non-finite = invalid.
        match_uv: (F, M, 2) float32 pixel coordinates of the correspondences.
        match_points: (F, M, 3) float32 their world points (metres).
        match_valid: (F, M) bool, which correspondences count.
    """

    depth_uv: Array
    depth: Array
    match_uv: Array
    match_points: Array
    match_valid: Array


class RefineResult(eqx.Module):
    """Result of a refinement (a pytree; batch axes come from vmap).

    Attributes:
        pose: refined ``T_world_cam`` of the last frame (jaxlie.SE3); the initial pose when
            ``ok`` is False.
        yaw_pose: (4,) ``(x, y, z, yaw)`` of ``pose`` (pitch and roll dropped).
        frame_poses: ``T_world_cam`` of every frame (jaxlie.SE3 with a leading (F,) axis):
            ``pose @ T_rel[t]``, the frames placed through the ego-motion and tilts.
        ok: bool scalar, the solve converged, enough residuals were valid, it did not diverge and
            the pose is determined (not degenerate).
        status: int32 scalar: 0 converged, 1 not converged, 2 bad input, 3 too few residuals,
            4 diverged, 5 degenerate, 6 poor fit (:mod:`jaxloc.sg2loc.refine`).
        steps: int32 scalar, optimiser steps.
        cost: float32 scalar, final robustified cost (``inf`` when not ``ok``).
        num_depth: int32 scalar, valid depth residuals at the initial pose (all frames).
        num_matches: int32 scalar, valid correspondences at the initial pose (all frames).
        position_std: float32 scalar, 1-sigma position uncertainty (metres) of the solved pose
            along its worst direction, from the Gauss-Newton information
            (:mod:`jaxloc.sg2loc.refine`); ``inf`` where undetermined or non-finite.
        rotation_std: float32 scalar, the same for the rotation (radians).
        inlier_fraction: float32 scalar in [0, 1], the fraction of the valid residual blocks at
            the solved pose (depth re-associated there) whose norm is at most
            ``config.inlier_threshold`` sigma (0 when none is valid).
    """

    pose: jaxlie.SE3
    yaw_pose: Array
    frame_poses: jaxlie.SE3
    ok: Array
    status: Array
    steps: Array
    cost: Array
    num_depth: Array
    num_matches: Array
    position_std: Array
    rotation_std: Array
    inlier_fraction: Array
