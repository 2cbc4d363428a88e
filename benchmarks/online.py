"""Latency per frame of the streaming SG2Loc filter (:func:`jaxloc.sg2loc.online.update`) beside
the bare jitted filter step on the same frames, in the same run.

For each image size (default 320x180 and 960x540, the paper's), a synthetic episode of the
default room and sensor settings; the stream runs at the paper's 2500 particles and the coarse
stride 20 (``SG2LocConfig`` defaults: the stream runs ``strides[0]``). Per frame, wall clock
until the estimate is ready:

* ``update``: what a user's loop waits for: the inputs' checks and transfers, the compiled step
  with the verdict and the relocalization policy, the new state;
* ``step``: :func:`jaxloc.sg2loc.step` alone, jitted, on the same frames and particles (the
  peer: the per-frame cost of one round of :func:`jaxloc.sg2loc.localize`).

The first frame is reported apart (all 2500 particles are rendered; KLD-sampling then keeps
~500); compile time is separate. Peak RSS is the process's.

``--check`` times, beside ``update``, what the two streaming checks add per frame: a depth-blind
stream's ``update``, the refinement with depth of the stream's estimate
(:func:`jaxloc.sg2loc.refine.refine_frame`, depth pixels every ``max(4, width // 96)``-th pixel;
``--check-budgets``: its rounds and steps, by default RefineConfig's 16 x 20 beside 4 x 10) and
the depth agreement at the refined pose (:func:`jaxloc.sg2loc.depth_agreement`, timed over the
whole sequence and divided by its frames); then the check of
``experiments/sg2loc_stream_refine.py`` refines the depth-blind estimate as well, and the check of
``experiments/sg2loc_stream_margin.py`` instead scores the refined pose and the depth-blind
estimate under the depth-blind model (timed as their render, :func:`jaxloc.sg2loc.render_batch` of
the two poses on the stream's ray grid; the scores' arithmetic on those rays is not timed).

    python benchmarks/online.py                        # 320x180 and 960x540, 10 frames
    python benchmarks/online.py --sizes 960x540 --frames 20
    python benchmarks/online.py --check
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import time

import jax
import numpy as np

from jaxloc.sg2loc import Frame, online, step
from jaxloc.synthetic.indoor import EpisodeConfig, SensorConfig, make_episode


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10


def motion_of(sequence, t: int) -> np.ndarray:
    return np.zeros(4, np.float32) if t == 0 else sequence.ego_motion[t - 1]


def time_size(width: int, height: int, frames: int, seed: int) -> dict:
    episode = make_episode(seed, frames, EpisodeConfig(sensor=SensorConfig(width, height)))
    seq, scene = episode.sequence, episode.scene
    state = online.init(jax.random.key(seed), scene, seq.camera)

    def update(state, t):
        return online.update(
            state, seq.patch_embeddings[t], motion_of(seq, t), seq.depth[t], seq.rgb[t], seq.tilt[t]
        )

    start = time.perf_counter()
    jax.block_until_ready(update(state, 0))  # compiles (the state is not advanced)
    compile_s = time.perf_counter() - start
    update_s, frames_in, localized = [], [], []
    for t in range(frames):
        start = time.perf_counter()
        state, estimate = update(state, t)
        jax.block_until_ready(estimate)
        update_s.append(time.perf_counter() - start)
        localized.append(bool(estimate.localized))

    # the peer: the same step, jitted alone, on the frames as update builds them
    config = state.config
    rows, cols = state.pixels
    h, w = config.grid.shape
    frames_in = [
        Frame(
            index=np.int32(t),
            motion=motion_of(seq, t),
            patch_embeddings=seq.patch_embeddings[t].reshape(config.grid.num_patches, -1),
            depth=seq.depth[t][rows, cols],
            rgb=seq.rgb[t][rows, cols].reshape(h, w, 3),
            tilt=seq.tilt[t],
        )
        for t in range(frames)
    ]
    jitted = jax.jit(step)
    particles = online.init(jax.random.key(seed), scene, seq.camera).particles
    jax.block_until_ready(jitted(jax.random.key(0), particles, frames_in[0], scene, config))
    step_s = []
    for t in range(frames):
        start = time.perf_counter()
        particles, info = jitted(jax.random.key(t), particles, frames_in[t], scene, config)
        jax.block_until_ready((particles, info))
        step_s.append(time.perf_counter() - start)
    return {
        "size": f"{width}x{height}",
        "rays": int(config.grid.uv.shape[0]),
        "compile": compile_s,
        "update_first": update_s[0],
        "update_rest": float(np.median(update_s[1:])) if frames > 1 else float("nan"),
        "step_first": step_s[0],
        "step_rest": float(np.median(step_s[1:])) if frames > 1 else float("nan"),
        "localized": sum(localized),
        "frames": frames,
    }


def time_check(width: int, height: int, frames: int, seed: int, budget: str) -> dict:
    """Median seconds per frame (after the first) of ``update`` and of what the check adds, with
    the refinement's ``budget`` ("ROUNDSxSTEPS": ``rounds`` and ``max_steps``)."""
    import jax.numpy as jnp

    from jaxloc.geometry import yaw_pose_to_se3
    from jaxloc.sg2loc import depth_agreement, render_batch
    from jaxloc.sg2loc.refine import RefineConfig, refine_frame

    episode = make_episode(seed, frames, EpisodeConfig(sensor=SensorConfig(width, height)))
    seq, scene = episode.sequence, episode.scene
    streams = {
        name: online.init(jax.random.key(seed), scene, seq.camera) for name in ("depth", "blind")
    }
    rounds, steps = (int(n) for n in budget.split("x"))
    refine_config = RefineConfig(depth_stride=max(4, width // 96), rounds=rounds, max_steps=steps)
    parts = {
        part: []
        for part in ("update", "blind update", "refinement", "blind refinement", "two-pose render")
    }
    render_two = jax.jit(render_batch, static_argnames=("engine", "differentiable"))
    acted = []
    for t in range(frames):
        estimates = {}
        for name, part in (("depth", "update"), ("blind", "blind update")):
            depth = seq.depth[t] if name == "depth" else None
            start = time.perf_counter()
            streams[name], estimates[name] = online.update(
                streams[name],
                seq.patch_embeddings[t],
                motion_of(seq, t),
                depth,
                seq.rgb[t],
                seq.tilt[t],
            )
            jax.block_until_ready(estimates[name])
            parts[part].append(time.perf_counter() - start)
        for name, part in (("depth", "refinement"), ("blind", "blind refinement")):
            start = time.perf_counter()
            T_init = yaw_pose_to_se3(estimates[name].pose, jnp.asarray(seq.tilt[t]))
            result = refine_frame(scene, seq.camera, T_init, refine_config, depth=seq.depth[t])
            jax.block_until_ready(result)
            parts[part].append(time.perf_counter() - start)
            if name == "depth":
                acted.append(np.where(result.ok, result.yaw_pose, estimates[name].pose))
        start = time.perf_counter()
        two = jnp.asarray(np.stack([acted[-1], estimates["blind"].pose]))
        grid = streams["blind"].config.grid
        tilt = jnp.asarray(seq.tilt[t])
        jax.block_until_ready(render_two(scene, two, seq.camera, grid, tilt, differentiable=False))
        parts["two-pose render"].append(time.perf_counter() - start)
    poses = jnp.asarray(np.stack(acted))
    jax.block_until_ready(depth_agreement(scene, seq, poses, 20))  # compiles
    start = time.perf_counter()
    jax.block_until_ready(depth_agreement(scene, seq, poses, 20))
    agreement = (time.perf_counter() - start) / frames
    out = {part: float(np.median(times[1:])) for part, times in parts.items()}
    out["agreement"] = agreement
    common = out["update"] + out["blind update"] + out["refinement"] + agreement
    out["twin check"] = common + out["blind refinement"]
    out["margin check"] = common + out["two-pose render"]
    return {"size": f"{width}x{height}", "budget": budget, **out}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="320x180,960x540", help="comma list of WxH")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--check", action="store_true", help="also time the streaming check")
    parser.add_argument(
        "--check-budgets",
        default="16x20,4x10",
        help="the check's refinement budgets, ROUNDSxSTEPS (16x20: RefineConfig's default)",
    )
    args = parser.parse_args(argv)
    device = jax.devices()[0]
    load = os.getloadavg()[0]
    rows = [
        time_size(*map(int, size.split("x")), args.frames, args.seed)
        for size in args.sizes.split(",")
    ]
    print("# Streaming SG2Loc: latency per frame (online.update vs the bare filter step)\n")
    print(
        f"- jax {jax.__version__} on {device.platform} ({device.device_kind}); "
        f"{os.cpu_count()} CPUs, {platform.processor() or platform.machine()}; load average "
        f"{load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end; peak RSS "
        f"{peak_rss_mib():.0f} MiB; 2500 particles, stride 20, {args.frames} frames, seed "
        f"{args.seed}"
    )
    print(
        "\n| image | rays/particle | compile s | update, first frame s | update, later frames s "
        "(median) | step alone, first s | step alone, later s (median) | update / step (later) "
        "| frames localized |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['size']} | {r['rays']} | {r['compile']:.1f} | {r['update_first']:.3f} | "
            f"{r['update_rest']:.3f} | {r['step_first']:.3f} | {r['step_rest']:.3f} | "
            f"{r['update_rest'] / r['step_rest']:.2f}x | {r['localized']} / {r['frames']} |"
        )
    if not args.check:
        return
    checks = [
        time_check(*map(int, size.split("x")), args.frames, args.seed, budget)
        for size in args.sizes.split(",")
        for budget in args.check_budgets.split(",")
    ]
    print(
        "\nThe streaming check per frame (median of the frames after the first, seconds; load "
        f"average {os.getloadavg()[0]:.1f} at the end):\n"
    )
    print(
        "| image | refinement rounds x steps | update | depth-blind update | refinement | "
        "depth-blind refinement | depth agreement | two-pose render | frame with the refined-twin "
        "check | / update | frame with the margin check | / update |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in checks:
        print(
            f"| {r['size']} | {r['budget']} | {r['update']:.3f} | {r['blind update']:.3f} | "
            f"{r['refinement']:.3f} | {r['blind refinement']:.3f} | {r['agreement']:.3f} | "
            f"{r['two-pose render']:.3f} | {r['twin check']:.3f} | "
            f"{r['twin check'] / r['update']:.1f}x | {r['margin check']:.3f} | "
            f"{r['margin check'] / r['update']:.1f}x |"
        )


if __name__ == "__main__":
    main()
