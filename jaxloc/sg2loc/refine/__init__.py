"""Visual 6-DoF pose refinement of SG2Loc's estimate (replaces SG2Loc's RoMa + PnP step).

Starting from the filter's 4-DoF estimate ``(x, y, z, yaw)`` plus the frame's known tilt, a robust
Levenberg-Marquardt solve (:func:`jaxloc.lsq.solve_pose`, updates
``T = T_init @ (SO3.exp(omega), t)``) refines ``T_world_cam`` with

(a) **depth-to-mesh residuals**: a strided subset of the depth image's pixels is back-projected with
    the intrinsics and the current pose, ``p_world = T_world_cam (depth * K^-1 [u, v, 1])``, and
    compared with the scene raycast along the pixel ray (point-to-plane): ``r = n . (p_world -
    p_hit)`` with ``p_hit`` the raycast hit and ``n`` the unit normal of the hit triangle. ``p_hit``
    lies on that triangle's plane, so this equals ``n . (p_world - v0)`` (``v0`` a corner of the
    triangle), which is how it is evaluated (no cancellation for long rays). The association
    (which triangle) is piecewise constant in the pose and carries no gradient; the residual is
    smooth for a fixed triangle. The solve alternates association and least squares (projective
    ICP, ``RefineConfig.rounds``), and associates within a small window of neighbouring rays
    (the hit nearest in 3-D to the back-projected point, :func:`associate_depth`), because pure
    projective association leaves points seen across an occlusion edge on the wrong surface, where
    their residual carries no information and the solve stalls (measured: 3 of 4 starts at 0.3 m /
    10 deg stalled 0.19 m off in height on a synthetic room frame; none with the window).
    Invalid pixels (depth 0 or non-finite), misses and grazing hits (``|n . d| < min_incidence``)
    get a zero residual. Residuals are divided by the depth noise
    ``depth_sigma_abs + depth_sigma_rel * depth``.
(b) **reprojection residuals** of user-given 2D-3D correspondences (pixel ``uv`` (M, 2), world
    points (M, 3), optional validity mask): ``(pi(T_world_cam^-1 X) - uv) / pixel_sigma``, one 2-D
    block per correspondence. Points closer than ``min_depth`` in front of the camera (or behind
    it), non-finite rows and masked rows get a zero residual (the division is guarded, so values and
    gradients stay finite).
(c) **both**: the blocks of (a) (as ``(r, 0)``) and (b) are stacked. The relative weighting is the
    noise model: each residual is divided by its standard deviation (metres for depth, pixels for
    reprojection), so the cost is the robustified negative log-likelihood of independent Gaussian
    noise, and the robust loss (``RefineConfig.loss``) acts on these normalised residuals (its scale
    is in units of sigma).

Sequences: with ``mode="sequence"`` every frame of a sequence contributes, through the known
ego-motion and tilts. The unknown is one SE(3) *anchor*, the last frame's ``T_world_cam``; frame t
is at ``T_anchor @ T_rel[t]``, where ``T_rel[t] = T_last^-1 T_t`` is fixed by the 4-DoF chain
(the last frame's estimate carried back through the ego-motion, :func:`frame_poses_from_last`) and
the frames' tilts. ``mode="last"`` uses the last frame alone.

Status codes of :class:`RefineResult` (failures are values; the pose is then the initial pose):
0 converged, 1 not converged (step budget or non-finite iterate), 2 non-finite or empty input
(from :func:`~jaxloc.lsq.solve_pose`), 3 too few valid residuals at the initial pose,
4 diverged (the solve moved farther than ``max_translation`` / ``max_rotation`` from the start),
5 degenerate (the data leave the pose undetermined along some direction, see below), 6 poor fit
(the solved pose explains too few of the observations, see below).

Degeneracy: a converged solve can still be wrong when the residuals do not constrain every degree
of freedom (a view of one wall leaves the translation along the wall and the rotation about its
normal free; a wall and the floor leave the translation along their intersection free), because
the solver then slides along the free direction while every residual stays zero. At the final
pose (and the last round's association) the Gauss-Newton information ``H = J^T W J`` of the
noise-normalised residuals in the pose tangent (``J`` (K, 6), ``W`` the robust loss's IRLS
weights) is the inverse covariance of the estimate under the configured noise model; the 1-sigma
standard deviations along the worst translation and rotation directions are
``sqrt(max eig [H^-1]_tt)`` (metres) and ``sqrt(max eig [H^-1]_rr)`` (radians) (marginal blocks,
so a free direction that mixes translation and rotation shows in both). They are reported as
``RefineResult.position_std`` / ``rotation_std``; above ``RefineConfig.max_position_std`` /
``max_rotation_std`` the result is status 5, not ok. This flags free directions only: a
well-constrained solve that converged to a wrong local minimum is not detected by it.

Fit check: at the solved pose the depth pixels are associated afresh and
``RefineResult.inlier_fraction`` is the fraction of the valid residual blocks within
``inlier_threshold`` sigma. A wrong local minimum leaves many observations unexplained; below
``RefineConfig.min_inlier_fraction`` the result is status 6, not ok. 0, the default, disables the
check, because the fraction at the true pose depends on how well the map's meshes model the sensed
surfaces and on the matcher's outlier rate, which only the user knows. Measured on synthetic
frames, whose depth is rendered from the map's own meshes: noise-free, 1.000 at every right answer
and 0.92 at the two wrong minima of depth-only refinement (``convergence.md`` in
``experiments/results/refine/``); with 2 % depth noise, holes and 10 % scene changes, 0.997-1.000
for depth alone at the refined pose, but 0.72-0.84 for matches with 20 % outliers (``table.md``).
Coarse meshes of real objects will sit lower; measure it on your own data before setting it.
"""

from jaxloc._lazy import public_names
from jaxloc.sg2loc.refine.config import (
    STATUS_BAD_INPUT as STATUS_BAD_INPUT,
    STATUS_CONVERGED as STATUS_CONVERGED,
    STATUS_DEGENERATE as STATUS_DEGENERATE,
    STATUS_DIVERGED as STATUS_DIVERGED,
    STATUS_NOT_CONVERGED as STATUS_NOT_CONVERGED,
    STATUS_POOR_FIT as STATUS_POOR_FIT,
    STATUS_TOO_FEW_RESIDUALS as STATUS_TOO_FEW_RESIDUALS,
    Observations as Observations,
    RefineConfig as RefineConfig,
    RefineResult as RefineResult,
)
from jaxloc.sg2loc.refine.frames import (
    correspondences as correspondences,
    depth_samples as depth_samples,
    frame_poses_from_last as frame_poses_from_last,
    refine as refine,
    refine_frame as refine_frame,
)
from jaxloc.sg2loc.refine.residuals import (
    DepthPlanes as DepthPlanes,
    associate_depth as associate_depth,
    depth_residuals as depth_residuals,
    point_to_plane as point_to_plane,
    reprojection_residuals as reprojection_residuals,
)
from jaxloc.sg2loc.refine.solve import (
    refine_pose as refine_pose,
)

__all__ = public_names(__file__)
