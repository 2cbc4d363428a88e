"""Where one SG2Loc filter step spends its time: hit search, hit attributes, views (depth / colour
gathers, patch majority), the semantic, depth and colour (SSIM) scores, and the weights / estimates
/ KLD resampling / injection, beside the whole step, per round stride.

Same data as ``benchmarks/filter_step.py`` (a synthetic room, 960x540 frames, 2500 particles). Each
stride is profiled on the state after its round's first step (the KLD count is then active, as on
every later frame). Parts that run per render chunk are timed on one chunk of
``StepConfig.chunk_size`` particles and multiplied by the number of chunks that hold active
particles; each part is its own jitted function, timed (best of ``--repeats``, wall and process
CPU) after compilation, so the parts' sum need not equal the whole step (the step fuses them): the
``rest`` row is the difference. The hit-search rays are the ones ``render_batch`` casts for the
chunk's poses, without the frame's small tilt. ``benchmarks/step_trace.py`` measures the parts
inside the compiled step instead (XLA:CPU only).

    python benchmarks/filter_profile.py                      # strides 20, 8, 4
    python benchmarks/filter_profile.py --strides 20 --engine jax
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from filter_step import FULL_PARTICLES, initial_state, load_data, make_data  # noqa: E402
from raycast import render_order_rays  # noqa: E402

from jaxloc import raycast, render_batch  # noqa: E402
from jaxloc.camera import stride_grid  # noqa: E402
from jaxloc.raycasting import hit_triangles
from jaxloc.raycasting.engines import resolve_engine
from jaxloc.sg2loc import KLDConfig, ObservationConfig, Region, StepConfig, frames_on_grid, step
from jaxloc.sg2loc._particles import inject_uniform, mle, update_weights, weighted_mean
from jaxloc.sg2loc._rendering import PACKET_SIZE
from jaxloc.sg2loc._resampling import kld_resample
from jaxloc.sg2loc._scores import match_patches, particle_log_likelihood


def best_of(fn, repeats):
    """Best-of-``repeats`` (wall s, CPU s) of ``fn()`` (which must block on its result)."""
    best = (math.inf, math.inf)
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        best = min(best, (wall, cpu))
    return best


def timed_jit(fn, args, repeats):
    compiled = jax.jit(fn).lower(*args).compile()
    jax.block_until_ready(compiled(*args))
    return best_of(lambda: jax.block_until_ready(compiled(*args)), repeats)


def stepped_state(scene, seq, poses_gt, stride: int, round_index: int, args):
    """The step of one round's stride: its config, the compiled step, the state after a step on
    frame 0 from the round's initial particles (the KLD count is then active), and frame 1."""
    grid = stride_grid(seq.camera, stride, *seq.patch_shape)
    region = Region.of_scene(scene)
    config = StepConfig(
        camera=seq.camera,
        grid=grid,
        observation=ObservationConfig(),
        kld=KLDConfig(),
        region=region,
        engine=args.engine,
        particle_chunk=args.chunk,
    )
    key = jax.random.key(0)
    state = initial_state(key, args.particles, round_index, region, poses_gt[0])
    frames = frames_on_grid(seq, grid)
    frame0, frame1 = (jax.tree.map(lambda a, t=t: a[t], frames) for t in (0, 1))
    compiled_step = jax.jit(step).lower(key, state, frame0, scene, config).compile()
    state, _ = compiled_step(jax.random.key(1), state, frame0, scene, config)
    return config, compiled_step, state, frame1


def profile_stride(scene, seq, poses_gt, stride, round_index, args):
    config, compiled_step, state, frame1 = stepped_state(
        scene, seq, poses_gt, stride, round_index, args
    )
    grid, region = config.grid, config.region
    step_time = best_of(
        lambda: jax.block_until_ready(
            compiled_step(jax.random.key(2), state, frame1, scene, config)
        ),
        args.repeats,
    )
    active = int(jnp.sum(state.active))
    chunk = config.chunk_size(args.particles)
    chunks = math.ceil(active / chunk) if chunk < args.particles else 1
    chunk_particles = chunk if chunk < args.particles else args.particles
    poses = np.asarray(state.poses)[:chunk_particles]
    if chunk >= args.particles:  # one call over every slot: inactive ones cast NaN rays
        poses = np.where(np.asarray(state.active)[:, None], poses, np.nan).astype(np.float32)
    origins, directions = render_order_rays(poses, seq.camera, grid, PACKET_SIZE, args.engine)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    valid = np.all(np.isfinite(origins), axis=1)
    finite_origins = np.where(valid[:, None], origins, 0.0).astype(np.float32)
    engine = resolve_engine(args.engine)

    parts = {}
    search = functools.partial(hit_triangles, engine=engine, packet_size=PACKET_SIZE)
    search_args = (scene, finite_origins, directions, valid)
    parts["hit search"] = timed_jit(search, search_args, args.repeats)
    # The step renders on raycast's values-only path; --differentiable profiles the other one.
    path = {"engine": engine, "differentiable": args.differentiable}
    cast = functools.partial(raycast, packet_size=PACKET_SIZE, **path)
    cast_time = timed_jit(cast, (scene, origins, directions), args.repeats)
    parts["hit values (t, barycentric, object) beyond the search"] = tuple(
        a - b for a, b in zip(cast_time, parts["hit search"], strict=True)
    )
    render = functools.partial(render_batch, **path)
    pose_args = (scene, jnp.asarray(poses), seq.camera, grid, frame1.tilt)
    render_time = timed_jit(render, pose_args, args.repeats)
    parts["views (depth, colour gathers, patch majority)"] = tuple(
        a - b for a, b in zip(render_time, cast_time, strict=True)
    )
    views = jax.jit(render)(*pose_args)
    h, w = grid.shape

    def scores(observation, views, frame):
        match = match_patches(frame.patch_embeddings, scene.embeddings, scene.object_valid)
        return jax.vmap(
            lambda obj, depth, color: particle_log_likelihood(
                observation, match, obj, depth, frame.depth, color.reshape(h, w, 3), frame.rgb
            )
        )(views.patch_object, views.depth, views.color)

    previous = (0.0, 0.0)
    for name, observation in (
        (
            "semantic score (patch match + per particle)",
            ObservationConfig(use_depth=False, use_color=False),
        ),
        ("depth score", ObservationConfig(use_depth=True, use_color=False)),
        ("colour score (SSIM)", ObservationConfig(use_depth=True, use_color=True)),
    ):
        total = timed_jit(functools.partial(scores, observation), (views, frame1), args.repeats)
        parts[name] = tuple(a - b for a, b in zip(total, previous, strict=True))
        previous = total
    per_chunk = list(parts)

    def bookkeeping(key, state, log_likelihood):
        state, _ = update_weights(state, log_likelihood)
        best, _ = mle(state)
        mean = weighted_mean(state)
        state, _ = kld_resample(key, state, config.kld)
        state = inject_uniform(
            key, state, config.inject_count, region.lo, region.hi, region.floor_z, config.heights
        )
        return state, best, mean

    log_likelihood = jnp.where(
        state.active, -jnp.arange(args.particles, dtype=jnp.float32), -jnp.inf
    )
    parts["weights, MLE, mean, KLD resampling, injection"] = timed_jit(
        bookkeeping, (jax.random.key(3), state, log_likelihood), args.repeats
    )
    for name in per_chunk:
        parts[name] = tuple(chunks * v for v in parts[name])
    summed = tuple(sum(v[i] for v in parts.values()) for i in range(2))
    parts["rest (step minus the parts: prediction, fusion, chunk loop)"] = tuple(
        a - b for a, b in zip(step_time, summed, strict=True)
    )
    return {
        "stride": stride,
        "rays": int(grid.uv.shape[0]),
        "active": active,
        "chunk": chunk_particles,
        "chunks": chunks,
        "step": step_time,
        "parts": parts,
    }


def add_step_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the profiled step: particles, frame size, strides, engine, chunk."""
    parser.add_argument("--particles", type=int, default=FULL_PARTICLES)
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--strides", default="20,8,4")
    parser.add_argument("--engine", default="auto")
    parser.add_argument("--chunk", type=int, default=None, help="StepConfig.particle_chunk")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_step_arguments(parser)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--differentiable",
        action="store_true",
        help="profile raycast's differentiable path (the step itself renders values only)",
    )
    args = parser.parse_args(argv)
    args.frames = 2
    with tempfile.TemporaryDirectory() as folder:
        info = make_data(args, Path(folder))
        scene, seq, poses_gt = load_data(Path(folder), args.width, args.height)
    load = os.getloadavg()[0]
    results = [
        profile_stride(scene, seq, poses_gt, int(s), r, args)
        for r, s in enumerate(args.strides.split(","))
    ]
    device = jax.devices()[0]
    print(
        f"# Filter step profile ({args.width}x{args.height}, {args.particles} particles, "
        f"engine {args.engine} = {resolve_engine(args.engine)}, "
        f"{'differentiable' if args.differentiable else 'values-only'} hit path)\n"
    )
    print(
        f"- {device.platform} ({device.device_kind}), {os.cpu_count()} CPUs; load average "
        f"{load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end; room of "
        f"{info['objects']} objects, {info['triangles']} triangles"
    )
    for r in results:
        wall, cpu = r["step"]
        print(
            f"\n## stride {r['stride']}: {r['rays']} rays per particle, {r['active']} active, "
            f"{r['chunks']} chunk(s) of {r['chunk']} particles; whole step {wall:.3f} s wall, "
            f"{cpu:.3f} s CPU\n"
        )
        print("| part | s wall | % of the step (wall) | s CPU |")
        print("|---|---|---|---|")
        for name, (part_wall, part_cpu) in r["parts"].items():
            print(f"| {name} | {part_wall:.3f} | {100 * part_wall / wall:.0f} % | {part_cpu:.3f} |")


if __name__ == "__main__":
    main()
