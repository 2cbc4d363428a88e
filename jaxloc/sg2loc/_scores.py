"""SG2Loc observation model: semantic, depth and SSIM colour scores, and the combined likelihood.

Every score is for ONE particle (vmap over particles); what depends only on the frame is computed
once by :func:`match_patches`. Named variants follow the paper (default) and the authors' code:

* semantic ``s`` in [0, 2]: ``"gated"`` (paper and code agree; default) or ``"soft"``;
* depth ``s_d``: ``"l1"`` (paper, default; at most 1, unbounded below) or ``"clipped"`` (authors'
  code; [0, 2]);
* colour ``s_i``: ``"paper"`` (mean SSIM clipped to [0, 1]; default) or ``"reference"``
  (authors' code: 2 * mean SSIM, [-2, 2]).

The likelihood is eq. (2): ``log L = -(S_max - S)^2 / (2 sigma^2)`` with
``S = s + lambda_depth * s_d + lambda_color * s_i`` and ``S_max`` the best attainable ``S``.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.camera import stride_grid_shape
from jaxloc.sg2loc._convert import as_float32, finite_scalar

#: Semantic score variants (``ObservationConfig.semantic_variant``; "gated" the default).
SEMANTIC_VARIANTS = ("gated", "soft")
#: Depth score variants (``ObservationConfig.depth_variant``): "l1" (paper, default), "clipped".
DEPTH_VARIANTS = ("l1", "clipped")
#: Colour score variants (``ObservationConfig.color_variant``): "paper" (default), "reference".
COLOR_VARIANTS = ("paper", "reference")

#: Best attainable semantic score (both variants).
SEMANTIC_MAX = 2.0
#: Best attainable depth score of each variant (also the score of a frame without valid depth).
DEPTH_MAX = {"l1": 1.0, "clipped": 2.0}
#: Best attainable colour score of each variant.
COLOR_MAX = {"paper": 1.0, "reference": 2.0}

#: SSIM's luminance constant ``(K1 L)^2`` for values in [0, 1] (Wang et al. 2004; K1 = 0.01).
SSIM_C1 = 0.01**2
#: SSIM's contrast constant ``(K2 L)^2`` for values in [0, 1] (K2 = 0.03).
SSIM_C2 = 0.03**2
#: Side of SSIM's box window (rays): a colour score needs a ray grid at least this big.
SSIM_WINDOW = 7


def largest_ssim_stride(width: int, height: int) -> int:
    """The largest stride whose ray grid (:func:`jaxloc.camera.stride_grid_shape`) on a
    ``width x height`` image holds SSIM's window, :data:`SSIM_WINDOW` rays a side (0: none, the
    image is smaller than the window)."""
    fits = (s for s in range(min(width, height), 0, -1) if _ssim_fits(s, width, height))
    return next(fits, 0)


def _ssim_fits(stride: int, width: int, height: int) -> bool:
    return min(stride_grid_shape(stride, width, height)) >= SSIM_WINDOW


def check_ssim_strides(
    strides, width: int, height: int, setting: str = "strides", otherwise: str | None = None
) -> None:
    """Raise a one-line ValueError unless every stride of ``strides`` casts at least SSIM's
    :data:`SSIM_WINDOW` x :data:`SSIM_WINDOW` rays on a ``width x height`` image (what the colour
    score needs). The message starts with ``setting``, the setting that fixes it
    (``"SG2LocConfig(strides=...)"``, a command-line option),
    names the largest stride that fits and ends with ``otherwise``, another way out (e.g. turning
    the colour score off)."""
    for stride in strides:
        if _ssim_fits(stride, width, height):
            continue
        rows, cols = stride_grid_shape(stride, width, height)
        largest = largest_ssim_stride(width, height)
        fix = f"use strides of at most {largest}"
        if not largest:
            fix = f"no stride fits an image under {SSIM_WINDOW} px a side"
        raise ValueError(
            f"{setting}: stride {stride} gives a {rows} x {cols} ray grid at {width} x {height}, "
            f"smaller than SSIM's {SSIM_WINDOW} x {SSIM_WINDOW} window; {fix}"
            + (f", or {otherwise}" if otherwise else "")
        )


def _check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


class PatchMatch(NamedTuple):
    """What the semantic score needs from one frame, computed once for all particles.

    Attributes:
        cosines: (P, O) float32 cosine similarity of patch p and object o; -1 for invalid
            objects and for zero-norm patch embeddings (so such pairs add nothing).
        predicted: (P,) int32 the patch's best-matching valid object (argmax of the cosine), -1
            when there is no valid object or the patch embedding is zero.
    """

    cosines: Array
    predicted: Array


def match_patches(
    patch_embeddings: Array, object_embeddings: Array, object_valid: Array
) -> PatchMatch:
    """Cosines of every patch with every object and each patch's predicted object.

    Args:
        patch_embeddings: (P, d) float query-image patch embeddings (any norm).
        object_embeddings: (O, d) float object embeddings (unit norm by contract; renormalised
            here anyway, zero rows count as invalid).
        object_valid: (O,) bool, which object slots are real objects.

    Returns:
        A :class:`PatchMatch`.
    """
    patch_embeddings = jnp.asarray(patch_embeddings)
    object_embeddings = jnp.asarray(object_embeddings)
    if patch_embeddings.ndim != 2 or object_embeddings.ndim != 2:
        raise ValueError(
            f"patch_embeddings (P, d) and object_embeddings (O, d) must be 2-D, got shapes "
            f"{patch_embeddings.shape} and {object_embeddings.shape}"
        )
    if patch_embeddings.shape[1] != object_embeddings.shape[1]:
        raise ValueError(
            f"embedding sizes differ: patches {patch_embeddings.shape}, "
            f"objects {object_embeddings.shape}"
        )
    if jnp.shape(object_valid) != object_embeddings.shape[:1]:
        raise ValueError(
            f"object_valid must have shape {object_embeddings.shape[:1]}, "
            f"got {jnp.shape(object_valid)}"
        )

    def unit(x: Array) -> tuple[Array, Array]:
        norm = jnp.linalg.norm(x, axis=-1, keepdims=True)
        nonzero = norm > 0.0
        return x / jnp.where(nonzero, norm, 1.0), nonzero[..., 0]

    patches, patch_ok = unit(patch_embeddings.astype(jnp.float32))
    objects, object_ok = unit(object_embeddings.astype(jnp.float32))
    object_ok = object_ok & jnp.asarray(object_valid, bool)
    usable = patch_ok[:, None] & object_ok[None, :]
    cosines = jnp.where(
        usable, jnp.clip(jnp.matmul(patches, objects.T, precision="highest"), -1.0, 1.0), -1.0
    )
    best = jnp.argmax(jnp.where(usable, cosines, -jnp.inf), axis=-1).astype(jnp.int32)
    predicted = jnp.where(jnp.any(usable, axis=-1), best, -1)
    return PatchMatch(cosines, predicted)


def semantic_score(match: PatchMatch, rendered_object: Array, variant: str = "gated") -> Array:
    """Semantic patch score ``s`` in [0, 2] of one particle (SG2Loc section 3.3).

    ``"gated"``: ``s = (1/P) sum_p [predicted_p == rendered_p] (cos(p, e_rendered_p) + 1)``.
    ``"soft"``: ``s = (1/P) sum_p [rendered_p is an object] (cos(p, e_rendered_p) + 1)``.
    Patches that render no object (-1) add 0 in both.

    Args:
        match: the frame's :class:`PatchMatch` (P patches, O objects).
        rendered_object: (P,) int32 dominant object of each patch for this particle, -1 = none.
        variant: ``"gated"`` or ``"soft"`` (static).

    Returns:
        float32 scalar.
    """
    _check_choice("semantic variant", variant, SEMANTIC_VARIANTS)
    num_patches, num_objects = match.cosines.shape
    if jnp.shape(rendered_object) != (num_patches,):
        raise ValueError(
            f"rendered_object must have shape ({num_patches},), got {jnp.shape(rendered_object)}"
        )
    rendered = jnp.asarray(rendered_object, jnp.int32)
    seen = (rendered >= 0) & (rendered < num_objects)
    safe = jnp.where(seen, rendered, 0)
    cosine = jnp.take_along_axis(match.cosines, safe[:, None], axis=1)[:, 0]
    counted = seen if variant == "soft" else seen & (match.predicted == rendered)
    return jnp.sum(jnp.where(counted, cosine + 1.0, 0.0)) / num_patches


class DepthScore(NamedTuple):
    """A depth score and the number of rays it rests on.

    Attributes:
        score: float32 scalar ``s_d``; the variant's maximum when ``num_valid == 0``.
        num_valid: int32 scalar, rays with a valid sensor depth.
    """

    score: Array
    num_valid: Array


def depth_score(
    rendered_depth: Array,
    sensor_depth: Array,
    variant: str = "l1",
    clip: Array | float = 0.5,
    miss_error: Array | float = 1.0,
) -> DepthScore:
    """Depth score ``s_d`` of one particle (SG2Loc section 3.4) over the rays of valid sensor depth.

    A sensor depth is valid when finite and > 0 (0 marks a hole); a rendered depth is a hit when
    finite and > 0 (+inf marks a miss). Both are z-depths in metres at the same rays.

    ``"l1"`` (paper): ``s_d = 1 - mean |D_render - D_sensor|``; a rendered miss counts as an error
    of ``miss_error`` metres (default 1 m, so a view of nothing scores 0). Unbounded below.
    ``"clipped"`` (authors' code): ``e = mean |clip(D_sensor - D_render, -clip, clip)|`` with a
    miss counting as ``clip``; ``s_d = 2 - 2 min(e, clip) / clip`` in [0, 2].

    A frame with no valid sensor depth carries no depth information: ``s_d`` is then the variant's
    maximum (1 or 2), so the depth term drops out of eq. (2) (its deficit ``S_max - S`` is 0), and
    ``num_valid`` is 0. Never NaN or inf; gradients with respect to ``rendered_depth`` are finite.

    Args:
        rendered_depth: (R,) float rendered depth of this particle (metres, +inf = miss).
        sensor_depth: (R,) float observed depth at the same rays (metres, 0 = invalid).
        variant: ``"l1"`` or ``"clipped"`` (static).
        clip: clip threshold of ``"clipped"`` (metres, traced, > 0).
        miss_error: error of a rendered miss in ``"l1"`` (metres, traced).
    """
    _check_choice("depth variant", variant, DEPTH_VARIANTS)
    if jnp.ndim(rendered_depth) != 1 or jnp.shape(rendered_depth) != jnp.shape(sensor_depth):
        raise ValueError(
            f"rendered_depth and sensor_depth must be (R,) of equal shape, got "
            f"{jnp.shape(rendered_depth)} and {jnp.shape(sensor_depth)}"
        )
    rendered = jnp.asarray(rendered_depth, jnp.float32)
    sensor = jnp.asarray(sensor_depth, jnp.float32)
    valid = jnp.isfinite(sensor) & (sensor > 0.0)
    hit = jnp.isfinite(rendered) & (rendered > 0.0)
    safe_sensor = jnp.where(valid, sensor, 0.0)
    safe_rendered = jnp.where(hit, rendered, 0.0)
    num_valid = jnp.sum(valid)
    denominator = jnp.maximum(num_valid, 1).astype(jnp.float32)
    if variant == "l1":
        error = jnp.where(hit, jnp.abs(safe_rendered - safe_sensor), miss_error)
        score = 1.0 - jnp.sum(jnp.where(valid, error, 0.0)) / denominator
    else:
        clip = jnp.asarray(clip, jnp.float32)
        error = jnp.where(hit, jnp.abs(jnp.clip(safe_sensor - safe_rendered, -clip, clip)), clip)
        mean_error = jnp.sum(jnp.where(valid, error, 0.0)) / denominator
        score = 2.0 - 2.0 * jnp.minimum(mean_error, clip) / clip
    score = jnp.where(num_valid > 0, score, DEPTH_MAX[variant])
    return DepthScore(score.astype(jnp.float32), num_valid.astype(jnp.int32))


def _box_mean(image: Array) -> Array:
    """Mean over every 7x7 window ('valid' positions) of a channel-first (c, h, w) image.

    Two separable window sums (``lax.reduce_window``, 7 rows, then 7 columns), which XLA keeps
    as passes of their own. Sums of 7 shifted slices, the same additions in the same order (the
    results are bit-identical), got the column pass fused into the row pass on XLA:CPU, which
    then recomputed every row sum 7 times (inside the paper-scale filter step, 0.26 s of a
    stride-4 step for the colour score against 0.17-0.18 s with the window sums:
    ``benchmarks/step_trace.py``).
    """
    ones = (1, 1, 1)
    rows = jax.lax.reduce_window(image, 0.0, jax.lax.add, (1, SSIM_WINDOW, 1), ones, "VALID")
    total = jax.lax.reduce_window(rows, 0.0, jax.lax.add, (1, 1, SSIM_WINDOW), ones, "VALID")
    return total / float(SSIM_WINDOW * SSIM_WINDOW)


def mean_ssim(rendered: Array, observed: Array) -> Array:
    """Mean SSIM (float32 scalar, in [-1, 1]) of two (h, w, 3) images with values in [0, 1].

    7x7 box windows at every position where the window fits (no padding), population
    (co)variances, ``C1 = 0.01^2``, ``C2 = 0.03^2``; averaged over window positions and channels.
    By construction this is skimage's ``structural_similarity(x, y, win_size=7, data_range=1,
    use_sample_covariance=False, channel_axis=-1)`` (skimage filters with reflect padding, then
    crops 3 pixels per side, which leaves exactly the windows that fit); skimage's default
    sample covariance differs by a factor 49/48 on the variances. Needs ``h, w >= 7``.
    """
    rendered = jnp.asarray(rendered, jnp.float32)
    observed = jnp.asarray(observed, jnp.float32)
    if rendered.ndim != 3 or rendered.shape != observed.shape:
        raise ValueError(
            f"rendered and observed must be (h, w, c) of equal shape, got {rendered.shape} "
            f"and {observed.shape}"
        )
    if min(rendered.shape[:2]) < SSIM_WINDOW:
        raise ValueError(
            f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {rendered.shape[:2]}"
        )
    rendered = jnp.moveaxis(rendered, -1, 0)
    observed = jnp.moveaxis(observed, -1, 0)
    mu_x, mu_y = _box_mean(rendered), _box_mean(observed)
    var_x = _box_mean(rendered * rendered) - mu_x * mu_x
    var_y = _box_mean(observed * observed) - mu_y * mu_y
    cov = _box_mean(rendered * observed) - mu_x * mu_y
    numerator = (2.0 * mu_x * mu_y + SSIM_C1) * (2.0 * cov + SSIM_C2)
    denominator = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return jnp.mean(numerator / denominator)


def color_score(rendered: Array, observed: Array, variant: str = "paper") -> Array:
    """SSIM colour score ``s_i`` of one particle (SG2Loc section 3.4).

    ``"paper"``: mean SSIM clipped to [0, 1]. ``"reference"`` (authors' code): 2 * mean SSIM.

    Args:
        rendered: (h, w, 3) float rendered colours of this particle in [0, 1].
        observed: (h, w, 3) float observed colours at the same rays in [0, 1].
        variant: ``"paper"`` or ``"reference"`` (static).
    """
    _check_choice("color variant", variant, COLOR_VARIANTS)
    ssim = mean_ssim(rendered, observed)
    return jnp.clip(ssim, 0.0, 1.0) if variant == "paper" else 2.0 * ssim


class ObservationConfig(eqx.Module):
    """Observation-model settings. Variants and switches are static; weights are traced floats.

    Attributes:
        semantic_variant: ``"gated"`` (default) or ``"soft"``.
        depth_variant: ``"l1"`` (paper, default) or ``"clipped"`` (authors' code).
        color_variant: ``"paper"`` (default) or ``"reference"``.
        use_depth, use_color: whether the depth / colour terms enter eq. (2).
        clip_total: clip ``S`` to [0, S_max] before the Gaussian (authors' code); default False.
        lambda_depth, lambda_color: weights of ``s_d`` and ``s_i`` in ``S`` (paper: 2 and 2, so
            that ``S_max = 6`` with the paper's ranges).
        sigma: width of the Gaussian on ``S_max - S``. Default 0.6: the paper gives 0.2 for the
            semantic-only likelihood on ``s`` in [0, 2] (section 3.3) and no value for eq. (2),
            whose range is three times larger; 0.6 is that 0.2 scaled to ``S_max = 6`` and is what
            the authors' code uses. For semantic only (no depth, no colour) use 0.2.
        depth_clip: clip threshold of the ``"clipped"`` depth variant (metres).
        depth_miss_error: error of a rendered miss in the ``"l1"`` depth variant (metres).
    """

    semantic_variant: str = eqx.field(static=True, default="gated")
    depth_variant: str = eqx.field(static=True, default="l1")
    color_variant: str = eqx.field(static=True, default="paper")
    use_depth: bool = eqx.field(static=True, default=True)
    use_color: bool = eqx.field(static=True, default=True)
    clip_total: bool = eqx.field(static=True, default=False)
    lambda_depth: Array = eqx.field(default=2.0, converter=as_float32)
    lambda_color: Array = eqx.field(default=2.0, converter=as_float32)
    sigma: Array = eqx.field(default=0.6, converter=as_float32)
    depth_clip: Array = eqx.field(default=0.5, converter=as_float32)
    depth_miss_error: Array = eqx.field(default=1.0, converter=as_float32)

    def __check_init__(self):
        _check_choice("semantic_variant", self.semantic_variant, SEMANTIC_VARIANTS)
        _check_choice("depth_variant", self.depth_variant, DEPTH_VARIANTS)
        _check_choice("color_variant", self.color_variant, COLOR_VARIANTS)
        for name in ("lambda_depth", "lambda_color", "sigma", "depth_clip", "depth_miss_error"):
            value = finite_scalar("ObservationConfig", name, getattr(self, name))
            if value is None:
                continue
            if name in ("sigma", "depth_clip") and not value > 0:
                raise ValueError(f"ObservationConfig.{name} must be positive, got {value}")
            if name.startswith("lambda") and not value >= 0:
                raise ValueError(f"ObservationConfig.{name} must be non-negative, got {value}")

    @classmethod
    def reference(cls) -> ObservationConfig:
        """The authors' code: clipped depth, 2 * SSIM, unit lambdas, sigma 0.6, S clipped."""
        return cls(
            depth_variant="clipped",
            color_variant="reference",
            clip_total=True,
            lambda_depth=1.0,
            lambda_color=1.0,
            sigma=0.6,
        )

    def max_total(self) -> Array:
        """``S_max``: the best attainable combined score (float32 scalar)."""
        total = jnp.asarray(SEMANTIC_MAX, jnp.float32)
        if self.use_depth:
            total = total + self.lambda_depth * DEPTH_MAX[self.depth_variant]
        if self.use_color:
            total = total + self.lambda_color * COLOR_MAX[self.color_variant]
        return total


def log_likelihood(
    config: ObservationConfig,
    semantic: Array,
    depth: Array | None = None,
    color: Array | None = None,
) -> Array:
    """Eq. (2) in log space: ``log L = -(S_max - S)^2 / (2 sigma^2)`` (float32, <= 0).

    ``S = semantic + lambda_depth * depth + lambda_color * color``, with the depth / colour terms
    present iff ``config.use_depth`` / ``config.use_color`` (their scores are then required).
    With ``config.clip_total`` ``S`` is clipped to [0, S_max] first.
    """
    total = jnp.asarray(semantic, jnp.float32)
    for name, enabled, score, weight in (
        ("depth", config.use_depth, depth, config.lambda_depth),
        ("color", config.use_color, color, config.lambda_color),
    ):
        if enabled:
            if score is None:
                raise ValueError(f"config.use_{name} is set but no {name} score was given")
            total = total + weight * score
    best = config.max_total()
    if config.clip_total:
        total = jnp.clip(total, 0.0, best)
    return -((best - total) ** 2) / (2.0 * config.sigma**2)


class Scores(NamedTuple):
    """The scores of one particle (float32 scalars; depth/colour 0 when unused)."""

    semantic: Array
    depth: Array
    color: Array
    log_likelihood: Array


def particle_log_likelihood(
    config: ObservationConfig,
    match: PatchMatch,
    rendered_object: Array,
    rendered_depth: Array | None = None,
    sensor_depth: Array | None = None,
    rendered_rgb: Array | None = None,
    observed_rgb: Array | None = None,
) -> Scores:
    """All scores and the log-likelihood of one particle; vmap over particles.

    Args:
        config: :class:`ObservationConfig`.
        match: the frame's :func:`match_patches` (P patches).
        rendered_object: (P,) int32 dominant object per patch, -1 = none.
        rendered_depth: (R,) rendered depths (metres; +inf miss); needed iff
            ``config.use_depth``.
        sensor_depth: (R,) sensor depths (metres; 0 invalid); needed iff ``config.use_depth``.
        rendered_rgb: (h, w, 3) rendered colours in [0, 1]; needed iff ``config.use_color``.
        observed_rgb: (h, w, 3) observed colours in [0, 1]; needed iff ``config.use_color``.
    """
    with jax.named_scope("semantic_score"):
        semantic = semantic_score(match, rendered_object, config.semantic_variant)
    depth = color = jnp.zeros((), jnp.float32)
    if config.use_depth:
        if rendered_depth is None or sensor_depth is None:
            raise ValueError("config.use_depth needs rendered_depth and sensor_depth")
        with jax.named_scope("depth_score"):
            depth = depth_score(
                rendered_depth,
                sensor_depth,
                config.depth_variant,
                config.depth_clip,
                config.depth_miss_error,
            ).score
    if config.use_color:
        if rendered_rgb is None or observed_rgb is None:
            raise ValueError("config.use_color needs rendered_rgb and observed_rgb")
        with jax.named_scope("color_score"):
            color = color_score(rendered_rgb, observed_rgb, config.color_variant)
    return Scores(semantic, depth, color, log_likelihood(config, semantic, depth, color))
