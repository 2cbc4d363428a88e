"""The coarse-to-fine rounds of :func:`~jaxloc.sg2loc.localize` as one program.

:func:`all_rounds` scans the rounds, each a ``lax.scan`` of the filter step over the frames. The
rounds share the prediction, the update and the re-initialisation; only the scoring, the one part
of a step that reads the ray grid, is chosen per round with ``lax.switch`` over the distinct
strides, so a first call traces and compiles each part once. :func:`carry_back` takes a round's
last estimate back to the first frame, where the next round starts.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.geometry import uncompose_yaw
from jaxloc.sg2loc._filter import scan_frames, score_active, step_scored_by
from jaxloc.sg2loc._particles import init_box, init_region
from jaxloc.sharding import pin_split


@jax.jit
def carry_back(pose: Array, ego_motion: Array) -> Array:
    """Carry the last frame's pose (4,) back to the first frame through ``ego_motion`` (T-1, 4)."""

    def back(current, motion):
        return uncompose_yaw(current, motion), None

    first, _ = jax.lax.scan(back, pose, ego_motion, reverse=True)
    return first


@eqx.filter_jit
def all_rounds(
    keys, frames, scene, configs, branches, boxes, ego_motion, capacity: int, mesh, progress
):
    """Every round of :func:`localize` as one program: a ``lax.scan`` over the rounds, each a
    ``lax.scan`` of the filter step over the frames.

    The rounds share the prediction, the update and the re-initialisation; only the scoring, the
    one part that reads the ray grid, is chosen per round (``lax.switch`` over the distinct
    grids), so each part is traced and compiled once.

    Args:
        keys: (R,) one PRNG key per round.
        frames: per distinct stride, the frames (stacked on T) sampled on its grid.
        configs: per distinct stride, its :class:`StepConfig` (the same but for the grid).
        branches: (R,) static, the distinct stride of each round (an index into ``configs``).
        boxes: ``(box_half_widths (B,), yaw_half_range)`` of the re-initialisations.
        ego_motion: (T-1, 4) the sequence's, to carry a round's last estimate back to frame 0.
        capacity, mesh: as for :func:`localize`.
        progress: a progress bar's id, or None (see :func:`~jaxloc.sg2loc.run_pass`).

    Returns:
        ``(info, infos, starts)``: the last round's per-frame :class:`StepInfo` (stacked on T),
        every round's (stacked on R, T), and the centre each round started around ((R, 4);
        round 0: NaN).
    """
    first = configs[0]
    region, (half_widths, yaw_half_range) = first.region, boxes
    rays = jnp.asarray([c.grid.uv.shape[0] for c in configs], jnp.int32)

    def initial(round_index, key, centre):
        def spread(_):
            lo, hi, floor_z = region.lo, region.hi, region.floor_z
            return init_region(key, capacity, lo, hi, floor_z, heights=first.heights)

        def boxed(_):
            half_width = jnp.full((3,), half_widths[jnp.maximum(round_index - 1, 0)])
            return init_box(key, capacity, centre, half_width, yaw_half_range)

        if len(branches) == 1:
            state = spread(None)
        else:
            state = jax.lax.cond(round_index == 0, spread, boxed, None)
        return state if mesh is None else pin_split(state, mesh)

    def scorer(branch, frame_on_grids):
        def on_grid(i):
            frame, config = frame_on_grids[i], configs[i]
            return lambda state, match: score_active(state, frame, scene, config, match)

        grids = [on_grid(i) for i in range(len(configs))]
        return lambda state, match: jax.lax.switch(branch, grids, state, match)

    def one_round(centre, round_):
        round_index, key, branch = round_
        key_init, key_run = jax.random.split(key)
        update = eqx.tree_at(lambda u: u.num_rays, first.update, rays[branch])

        def step_frame(key_t, state, frame_on_grids):
            score = scorer(branch, frame_on_grids)
            return step_scored_by(key_t, state, frame_on_grids[0], scene, first, update, score)

        state = initial(round_index, key_init, centre)
        index = frames[0].index
        _, infos = scan_frames(key_run, state, frames, index, step_frame, progress, mesh)
        return carry_back(infos.mle[-1], ego_motion), (infos, centre)

    indices = jnp.arange(len(branches), dtype=jnp.int32)
    round_xs = (indices, keys, jnp.asarray(branches, jnp.int32))
    start = jnp.full((4,), jnp.nan, jnp.float32)
    _, (infos, starts) = jax.lax.scan(one_round, start, round_xs)
    return jax.tree.map(lambda a: a[-1], infos), infos, starts
