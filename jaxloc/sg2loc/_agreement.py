"""Depth agreement: how much of a recording's depth a pose explains in the map.

A check of estimates that were chosen without the depth: the share of a frame's rays whose sensor
depth the map, rendered at the estimate, reproduces. An estimate of a filter that scored the depth
was fitted to it, and a look-alike wrong place fits much of it too; an estimate chosen without it
(a depth-blind filter: :class:`~jaxloc.sg2loc.ObservationConfig` ``use_depth=False``) cannot fit
it, so a wrong place fails the check (the SG2Loc guide, "A check the pose was not fitted to",
gives the recipe and what it measured).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.camera import stride_grid
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._convert import as_float32
from jaxloc.sg2loc._rendering import render
from jaxloc.sg2loc._sequence import FrameSequence, frames_on_grid


class AgreementConfig(eqx.Module):
    """Tolerance of :func:`depth_agreement`: a ray agrees when the rendered z-depth is within
    ``absolute + relative * d`` of the sensor's depth ``d``.

    Attributes:
        absolute: float32 metres (default 0.05).
        relative: float32 fraction of the sensor depth (default 0.05).
    """

    absolute: Array = eqx.field(default=0.05, converter=as_float32)
    relative: Array = eqx.field(default=0.05, converter=as_float32)


def agreeing_share(rendered: Array, sensor: Array, config: AgreementConfig) -> Array:
    """The share of one frame's rays that agree (float32 in [0, 1]): ``rendered`` (R,) z-depth at
    the pose (+inf on a miss, which never agrees), ``sensor`` (R,) the sensor's (0 or non-finite:
    no depth, left out). 0 when no ray has depth."""
    valid = jnp.isfinite(sensor) & (sensor > 0.0)
    error = jnp.abs(jnp.where(jnp.isfinite(rendered), rendered, jnp.inf) - sensor)
    agree = valid & (error <= config.absolute + config.relative * sensor)
    return jnp.sum(agree) / jnp.maximum(jnp.sum(valid), 1)


def depth_agreement(
    scene: SceneGraph,
    sequence: FrameSequence,
    poses: Array,
    stride: int,
    config: AgreementConfig | None = None,
    *,
    engine: str = "auto",
) -> Array:
    """Per frame, the share of the rays with sensor depth whose depth the map reproduces at the
    frame's pose (:class:`AgreementConfig`).

    Args:
        scene: the map.
        sequence: the recording, with depth (and its known tilts, used for the rays).
        poses: (T, 4) float32 ``T_world_cam`` as (x, y, z, yaw), one per frame (an estimate of
            :func:`~jaxloc.sg2loc.localize`: ``result.poses``).
        stride: pixel stride of the rays (static), e.g. the last of ``SG2LocConfig.strides``.
        config: the tolerance (traced leaves; default 5 cm + 5 %).
        engine: nearest-hit engine of the rendering (static; see :func:`jaxloc.raycast`).

    Returns:
        (T,) float32 in [0, 1]; 0 for a frame without valid depth.

    Raises:
        ValueError: a sequence without depth, or ``poses`` not of shape (T, 4).
    """
    if sequence.depth is None:
        raise ValueError("depth_agreement needs a sequence with depth (sequence.depth is None)")
    if jnp.shape(poses) != (sequence.num_frames, 4):
        raise ValueError(
            f"poses must have shape ({sequence.num_frames}, 4) = one (x, y, z, yaw) per frame, "
            f"got {jnp.shape(poses)}"
        )
    config = AgreementConfig() if config is None else config
    return _agreement(scene, sequence, poses, config, int(stride), engine)


@functools.partial(jax.jit, static_argnums=(4, 5))
def _agreement(scene, sequence, poses, config, stride: int, engine: str) -> Array:
    grid = stride_grid(sequence.camera, stride, *sequence.patch_shape)
    frames = frames_on_grid(sequence, grid)

    def one(pose, tilt, sensor):
        view = render(scene, pose, sequence.camera, grid, tilt, engine=engine, differentiable=False)
        return agreeing_share(view.depth, sensor, config)

    return jax.vmap(one)(jnp.asarray(poses, jnp.float32), frames.tilt, frames.depth)
