"""Long runs: a 1000-frame SG2Loc filter sequence and 10 000 M2Loc LiDAR queries.

Checks what a long deployment needs and a short test cannot show: no retrace (trace counts of the
jitted functions stay at one per shape for the whole run) and flat memory (the process's resident
set size, sampled from ``/proc/self/status`` along the run, stops growing after the first chunk).

* SG2Loc: one synthetic indoor episode (seed 1000, 160x90 images, d = 128 embeddings), a
  ``capacity``-particle filter on the 9x16 patch grid (one ray per patch), random-particle
  injection every 5th frame, run as ``lax.scan`` chunks of ``--chunk`` frames through one jitted
  :func:`jaxloc.sg2loc.run_pass` (the state is carried from chunk to chunk).
* M2Loc: ``--queries`` scan-like queries (``make_query``, at most 24 kept map vertices) of a
  synthetic dense outdoor world (seed 1000), each through
  :func:`jaxloc.m2loc.localize_scan` (TripletLoc configuration) with a fixed ``query_capacity``
  of 32.

    JAX_PLATFORMS=cpu python benchmarks/long_run.py --frames 1000 --queries 10000 \\
        --out benchmarks/results/long_run_cpu.md
"""

from __future__ import annotations

import argparse
import collections
import os
import platform
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from jaxloc.camera import patch_grid
from jaxloc.geometry import ego_motion
from jaxloc.m2loc import build_map, localization_errors, localize_scan, tripletloc_config
from jaxloc.sg2loc import (
    Frame,
    KLDConfig,
    ObservationConfig,
    Region,
    StepConfig,
    frames_on_grid,
    run_pass,
)
from jaxloc.sg2loc._particles import init_region
from jaxloc.synthetic.indoor import EpisodeConfig, RoomConfig, SensorConfig, make_episode
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

TRACES = {"run_pass": 0}


def _counted_run_pass(key, state, frames, scene, config):
    TRACES["run_pass"] += 1
    return run_pass(key, state, frames, scene, config)


RUN_PASS = jax.jit(_counted_run_pass)

#: XLA compilations of this process by function name (``jax.monitoring``).
COMPILED: collections.Counter[str] = collections.Counter()
jax.monitoring.register_event_duration_secs_listener(
    lambda event, _, **kw: (
        COMPILED.update([kw.get("fun_name", "?")])
        if event == "/jax/core/compile/backend_compile_duration"
        else None
    )
)


def memory_mib() -> tuple[float, float]:
    """(current RSS, peak RSS) of this process in MiB, from /proc/self/status."""
    fields = {}
    with open("/proc/self/status") as status:
        for line in status:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                fields[key] = int(value.split()[0]) / 1024.0
    return fields["VmRSS"], fields["VmHWM"]


def log(message: str) -> None:
    print(message, flush=True)


def lapped_frames(episode, grid, num_frames: int) -> tuple[Frame, np.ndarray]:
    """``num_frames`` frames that loop over the episode's trajectory (laps of L frames).

    Frame ``t`` shows episode frame ``t % L``; its index is ``t`` and its motion is the noisy
    ego-motion of the episode inside a lap, and the exact ego-motion from the last pose of a lap to
    the first pose at the start of the next one (a jump, correctly reported). Returns the frames
    and the ground-truth poses (num_frames, 4).
    """
    frames = frames_on_grid(episode.sequence, grid)
    laps = -(-num_frames // episode.sequence.num_frames)
    poses = np.asarray(episode.poses_gt)
    motion = np.asarray(frames.motion).copy()
    motion[0] = np.asarray(ego_motion(poses[-1], poses[0]))
    source = np.arange(num_frames) % episode.sequence.num_frames
    looped = jax.tree.map(lambda a: np.asarray(a)[source], frames)
    looped = eqx.tree_at(lambda f: (f.index, f.motion), looped,
                         (np.arange(num_frames, dtype=np.int32),
                          np.tile(motion, (laps, 1))[:num_frames]))  # fmt: skip
    return looped, poses[source]


def filter_run(num_frames: int, chunk: int, capacity: int, lap: int, checkpoint) -> dict:
    start = time.perf_counter()
    config = EpisodeConfig(
        room=RoomConfig(embedding_dim=128),
        sensor=SensorConfig(width=160, height=90),
    )
    episode = make_episode(1000, lap, config)
    scene = episode.scene
    camera = episode.sequence.camera
    step_config = StepConfig(
        camera=camera,
        grid=patch_grid(camera, 9, 16),
        observation=ObservationConfig(),
        kld=KLDConfig(min_particles=capacity // 4, max_particles=capacity),
        region=Region.of_scene(scene),
        inject_count=capacity // 10,
    )
    frames, poses_gt = lapped_frames(episode, step_config.grid, num_frames)
    build_s = time.perf_counter() - start
    log(f"filter: episode of {lap} frames built in {build_s:.1f} s")
    region = step_config.region
    state = init_region(jax.random.key(1000), capacity, region.lo, region.hi, region.floor_z)
    key = jax.random.key(1001)
    samples, estimates, degenerate = [], [], 0
    run_start = time.perf_counter()
    for c, first in enumerate(range(0, num_frames, chunk)):
        # a last, shorter chunk would be a new shape: keep chunks equal (num_frames % chunk == 0)
        part = jax.tree.map(lambda a, first=first: a[first : first + chunk], frames)
        chunk_start = time.perf_counter()
        state, info = RUN_PASS(jax.random.fold_in(key, c), state, part, scene, step_config)
        mle = np.asarray(info.mle)
        seconds = time.perf_counter() - chunk_start
        estimates.append(mle)
        degenerate += int(np.sum(np.asarray(info.degenerate)))
        rss, peak = memory_mib()
        samples.append((first + chunk, seconds, rss, peak, TRACES["run_pass"]))
        log(
            f"filter: frames {first + chunk}/{num_frames}  {seconds:.1f} s  "
            f"RSS {rss:.0f} MiB  peak {peak:.0f} MiB  traces {TRACES['run_pass']}"
        )
        checkpoint(_filter_result(samples, build_s, run_start, estimates, poses_gt, degenerate,
                                  scene))  # fmt: skip
    return _filter_result(samples, build_s, run_start, estimates, poses_gt, degenerate, scene)


def _filter_result(samples, build_s, run_start, estimates, poses_gt, degenerate, scene) -> dict:
    run_s = time.perf_counter() - run_start
    estimates = np.concatenate(estimates)
    errors = np.linalg.norm(estimates[:, :3] - poses_gt[: len(estimates), :3], axis=1)
    return {
        "samples": samples,
        "build_s": build_s,
        "run_s": run_s,
        "errors": errors,
        "degenerate": degenerate,
        "triangles": scene.num_triangles,
        "objects": scene.num_objects,
        "any_nan": bool(np.isnan(estimates).any()),
    }


def query_run(num_queries: int, every: int, checkpoint) -> dict:
    world = make_outdoor_world("dense", seed=1000)
    config = tripletloc_config(query_capacity=32)
    triplet_map = build_map(world.points, world.labels, config, world.road_normals)
    rng = np.random.default_rng(1000)
    samples, times, successes, sizes = [], [], 0, []
    run_start = time.perf_counter()
    for i in range(1, num_queries + 1):
        q = make_query(world.points, world.labels, world.road_normals, rng, max_kept=24)
        sizes.append(len(q.points))
        tic = time.perf_counter()
        result = localize_scan(triplet_map, None, q.points, q.labels)
        times.append(time.perf_counter() - tic)
        rte, rre = localization_errors(result.pose, q.T_map_scan)
        successes += bool(result.valid and rte < 7.5 and rre < 10.0)
        if i % every == 0 or i == 1:
            rss, peak = memory_mib()
            compiled = (COMPILED["jit(describe_query)"], COMPILED["jit(registered)"])
            samples.append((i, rss, peak, *compiled))
            log(
                f"queries: {i}/{num_queries}  RSS {rss:.0f} MiB  peak {peak:.0f} MiB  "
                f"compilations {compiled}  median {1e3 * np.median(times[-every:]):.1f} ms"
            )
            checkpoint(_query_result(samples, run_start, times, successes, sizes, world))
    return _query_result(samples, run_start, times, successes, sizes, world)


def _query_result(samples, run_start, times, successes, sizes, world) -> dict:
    return {
        "samples": samples,
        "run_s": time.perf_counter() - run_start,
        "times": np.asarray(times),
        "success": successes / len(times),
        "sizes": np.asarray(sizes),
        "map_vertices": len(world.points),
    }


def report(args, filt: dict | None, queries: dict | None) -> str:
    command = "JAX_PLATFORMS=cpu python " + " ".join(sys.argv)
    lines = [
        "# Long runs: no retrace, flat memory (CPU)",
        "",
        f"Command: `{command}`",
        "",
        f"jax {jax.__version__}, {jax.devices()[0]}, {os.cpu_count()} CPUs shared with other "
        f"sessions (load average {os.getloadavg()[0]:.1f} at the end), python "
        f"{platform.python_version()}. Times are wall-clock and noisy; memory is this process's "
        "RSS (VmRSS) and peak RSS (VmHWM) from /proc/self/status.",
        "",
    ]
    if filt is not None:
        s = filt["samples"]
        rss = np.array([row[2] for row in s])
        lines += [
            f"## SG2Loc: {s[-1][0]} of {args.frames} frames done, {args.capacity} particles, "
            f"chunks of {args.chunk}",
            "",
            f"Episode seed 1000 at 160x90, d = 128, {args.lap} frames looped (the exact ego-motion "
            "joins the last pose of a lap to the first), "
            f"{filt['objects']} objects, "
            f"{filt['triangles']} triangles (built in {filt['build_s']:.0f} s); 9x16 patch grid "
            f"(144 rays per particle); injection of {args.capacity // 10} particles every 5th "
            "frame.",
            "",
            f"- traces of the jitted `run_pass`: {s[-1][4]} for {len(s)} chunks",
            f"- RSS after chunk 1: {rss[0]:.0f} MiB; after the last chunk: {rss[-1]:.0f} MiB; "
            f"max over chunks 2..: {rss[1:].max() if len(rss) > 1 else rss[0]:.0f} MiB; "
            f"growth from chunk 2 to the end: {rss[-1] - rss[min(1, len(rss) - 1)]:+.0f} MiB",
            f"- total {filt['run_s']:.0f} s (first chunk includes compilation: {s[0][1]:.0f} s); "
            f"after it {np.mean([row[1] for row in s[1:]]) / args.chunk:.3f} s per frame"
            if len(s) > 1
            else f"- total {filt['run_s']:.0f} s",
            f"- NaN in any estimate: {filt['any_nan']}; frames with degenerate weights: "
            f"{filt['degenerate']}",
            f"- MLE position error (information only; a {args.capacity}-particle filter is not the "
            f"paper's setting): median {np.median(filt['errors']):.2f} m, frames under 0.25 m: "
            f"{np.mean(filt['errors'] < 0.25):.2f}",
            "",
            "| frames done | chunk s | RSS MiB | peak RSS MiB | traces |",
            "|---|---|---|---|---|",
        ]
        lines += [f"| {a} | {b:.1f} | {c:.0f} | {d:.0f} | {e} |" for a, b, c, d, e in s]
        lines.append("")
    if queries is not None:
        s = queries["samples"]
        rss = np.array([row[1] for row in s])
        t = 1e3 * queries["times"]
        lines += [
            f"## M2Loc: {len(t)} of {args.queries} queries through `localize_scan`",
            "",
            f"Synthetic dense world seed 1000 ({queries['map_vertices']} vertices), TripletLoc "
            f"(one scale), query_capacity 32; query sizes {queries['sizes'].min()}-"
            f"{queries['sizes'].max()} "
            f"(median {np.median(queries['sizes']):.0f}).",
            "",
            f"- compilations: describe_query {s[-1][3]}, the query {s[-1][4]} for {len(t)} queries",
            f"- RSS after query 1: {rss[0]:.0f} MiB; after query {s[1][0] if len(s) > 1 else 1}: "
            f"{rss[min(1, len(rss) - 1)]:.0f} MiB; at the end: {rss[-1]:.0f} MiB",
            f"- per query (wall, incl. host validation and the first compile): median "
            f"{np.median(t):.1f} ms, p90 {np.percentile(t, 90):.1f} ms, first {t[0]:.0f} ms; "
            f"total {queries['run_s']:.0f} s",
            f"- success (valid, RTE < 7.5 m, RRE < 10 deg): {queries['success']:.3f}",
            "",
            "| queries done | RSS MiB | peak RSS MiB | describe compiles | query compiles |",
            "|---|---|---|---|---|",
        ]
        lines += [f"| {a} | {b:.0f} | {c:.0f} | {d} | {e} |" for a, b, c, d, e in s]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--chunk", type=int, default=50)
    parser.add_argument("--capacity", type=int, default=200)
    parser.add_argument("--lap", type=int, default=100, help="frames of the looped episode")
    parser.add_argument("--queries", type=int, default=10000)
    parser.add_argument("--every", type=int, default=500, help="memory sample every N queries")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.frames and args.frames % args.chunk:
        parser.error("--frames must be a multiple of --chunk (one compiled chunk shape)")
    parts = {"filter": None, "queries": None}

    def checkpoint(name):
        def write(result):
            parts[name] = result
            if args.out is not None:
                args.out.parent.mkdir(parents=True, exist_ok=True)
                tmp = args.out.with_suffix(".tmp")
                tmp.write_text(report(args, parts["filter"], parts["queries"]) + "\n")
                tmp.replace(args.out)

        return write

    if args.queries:
        checkpoint("queries")(query_run(args.queries, args.every, checkpoint("queries")))
    if args.frames:
        result = filter_run(args.frames, args.chunk, args.capacity, args.lap, checkpoint("filter"))
        checkpoint("filter")(result)
    print(report(args, parts["filter"], parts["queries"]))


if __name__ == "__main__":
    main()
