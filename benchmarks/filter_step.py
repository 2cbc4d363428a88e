"""Seconds per frame and peak memory of one jitted SG2Loc filter step
(:func:`jaxloc.sg2loc.step`).

The paper's scale: 2500 particles on 960x540 images of a synthetic room
(:mod:`jaxloc.synthetic.indoor`, default room and sensor settings), for

* ``stride 20``: one pass = one step of round 0 (48 x 27 = 1296 rays per particle);
* ``all rounds``: one step at each of the default :class:`~jaxloc.sg2loc.SG2LocConfig` strides
  (20, 8, 4), summed: the per-frame cost of the full coarse-to-fine method (every round filters
  every frame once);
* ``patch 16x9``: the 9 x 16 patch grid with one ray per patch (144 rays per particle).

Each case runs in a fresh child process (so ``ru_maxrss`` is that case's own peak): it compiles
the step ahead of time (``jax.jit(step).lower(...).compile()``, timed separately), then steps
through the frames, blocking on every result. Times are wall clock AND process CPU time
(``time.process_time``, all threads), since the machine may be shared. Peak memory is
``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of the child and, where the backend reports it,
``jax.devices()[0].memory_stats()['peak_bytes_in_use']``. Round 0 starts from the paper's floor
initialisation; later rounds from the paper's boxes around the true first pose (half-widths 0.8
and 0.4 m). Only the active particles are rendered, in chunks of ``--chunk`` particles (default:
``jaxloc.sg2loc._filter.default_chunk_rays`` rays per chunk; ``--chunk 0`` renders every slot in
one call, the behaviour before chunking), with the nearest-hit engine ``--engine``. With
``--particles`` or the image size reduced, the table adds a column scaled linearly to the full
size, labelled as an estimate.

    python benchmarks/filter_step.py                                   # the full benchmark
    python benchmarks/filter_step.py --particles 200 --frames 2        # a quick run
    python benchmarks/filter_step.py --cases stride --strides 20       # the coarse pass only
    python benchmarks/filter_step.py --engine jax --chunk 0            # pure JAX, all slots at once
    python benchmarks/filter_step.py --baseline /tmp/jaxloc-base       # beside an older checkout
    python benchmarks/filter_step.py --cases stride --depth-blind      # and without the depth score

``--baseline`` runs every case a second time with an older jaxloc checkout first on the child's
``PYTHONPATH`` (``git worktree add /tmp/jaxloc-base <commit>``), alternating the two, and labels
each row with its tree.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FULL_PARTICLES = 2500
FULL_SIZE = (960, 540)
BOX_HALF_WIDTHS = (0.8, 0.4)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--particles", type=int, default=FULL_PARTICLES, help="particle capacity")
    parser.add_argument("--frames", type=int, default=3, help="frames stepped per case")
    parser.add_argument("--width", type=int, default=FULL_SIZE[0])
    parser.add_argument("--height", type=int, default=FULL_SIZE[1])
    parser.add_argument(
        "--strides", default="20,8,4", help="comma-separated strides of the rounds (paper 20,8,4)"
    )
    parser.add_argument(
        "--cases",
        default="stride,patch",
        help="comma-separated: 'stride' (every stride of --strides) and/or 'patch' (16x9 grid)",
    )
    parser.add_argument("--seed", type=int, default=0, help="synthetic room / episode seed")
    parser.add_argument(
        "--engine", default="auto", help="nearest-hit engine: auto, jax, embree or warp"
    )
    parser.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="particles per render chunk (default: by default_chunk_rays; 0: every slot at once)",
    )
    parser.add_argument(
        "--min-particles",
        type=int,
        default=None,
        help="KLDConfig.min_particles (default 500; --particles keeps every slot active)",
    )
    parser.add_argument(
        "--baseline", type=Path, default=None, help="an older jaxloc checkout to run beside"
    )
    parser.add_argument(
        "--depth-blind",
        action="store_true",
        help="also run every case without the depth score (the depth-blind check's filter)",
    )
    parser.add_argument("--without-depth", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--data", default=None, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


# ----------------------------------------------------------------------------- data


def make_data(args: argparse.Namespace, folder: Path) -> dict:
    """Build the episode once (host side), save the map and the sequence for the children."""
    import numpy as np

    from jaxloc.io.scene_map import save_scene
    from jaxloc.synthetic.indoor import EpisodeConfig, SensorConfig, make_episode

    start = time.perf_counter()
    config = EpisodeConfig(sensor=SensorConfig(width=args.width, height=args.height))
    episode = make_episode(args.seed, args.frames, config)
    seq = episode.sequence
    save_scene(episode.scene, folder / "scene.npz")
    np.savez(
        folder / "sequence.npz",
        patch_embeddings=seq.patch_embeddings,
        ego_motion=seq.ego_motion,
        depth=seq.depth,
        rgb=seq.rgb,
        tilt=seq.tilt,
        poses_gt=episode.poses_gt,
        camera=np.array([seq.camera.fx, seq.camera.fy, seq.camera.cx, seq.camera.cy]),
    )
    return {
        "seconds": time.perf_counter() - start,
        "objects": int(episode.scene.num_objects),
        "triangles": int(episode.scene.num_triangles),
        "room": [round(float(x), 2) for x in episode.room.size],
    }


def load_data(folder: Path, width: int, height: int):
    import numpy as np

    from jaxloc import Camera, FrameSequence
    from jaxloc.io.scene_map import load_scene

    with np.load(folder / "sequence.npz") as data:
        arrays = {key: data[key] for key in data.files}
    camera = Camera(*(float(v) for v in arrays["camera"]), width, height)
    seq = FrameSequence(
        camera,
        arrays["patch_embeddings"],
        arrays["ego_motion"],
        depth=arrays["depth"],
        rgb=arrays["rgb"],
        tilt=arrays["tilt"],
    )
    return load_scene(folder / "scene.npz"), seq, arrays["poses_gt"]


# ----------------------------------------------------------------------------- one case


def peak_rss_mib() -> float:
    """This process's peak resident set size in MiB (Linux reports KiB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10


def device_peak_mib():
    import jax

    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 - backends without memory statistics
        return None
    if not stats or "peak_bytes_in_use" not in stats:
        return None
    return stats["peak_bytes_in_use"] / 2**20


def initial_state(key, particles: int, round_index: int, region, first_pose):
    """Round 0: the paper's floor initialisation; later rounds: its box around the true first
    pose (half-widths :data:`BOX_HALF_WIDTHS`)."""
    import jax.numpy as jnp

    from jaxloc.sg2loc._particles import init_box, init_region

    if round_index == 0:
        return init_region(key, particles, region.lo, region.hi, region.floor_z)
    half = BOX_HALF_WIDTHS[min(round_index, len(BOX_HALF_WIDTHS)) - 1]
    return init_box(key, particles, jnp.asarray(first_pose), jnp.full((3,), half))


def run_case(args: argparse.Namespace) -> dict:
    """Compile and time one step configuration (runs in the child process)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxloc.camera import patch_grid, stride_grid
    from jaxloc.sg2loc import KLDConfig, ObservationConfig, Region, StepConfig, frames_on_grid, step

    scene, seq, poses_gt = load_data(Path(args.data), args.width, args.height)
    rows, cols = seq.patch_shape
    kind, _, value = args.child.partition(":")
    strides = [int(s) for s in args.strides.split(",")]
    if kind == "patch":
        grid = patch_grid(seq.camera, rows, cols, 1)
    else:
        grid = stride_grid(seq.camera, int(value), rows, cols)
    region = Region.of_scene(scene)
    config = StepConfig(
        camera=seq.camera,
        grid=grid,
        observation=ObservationConfig(use_depth=not args.without_depth),
        kld=KLDConfig()
        if args.min_particles is None
        else KLDConfig(min_particles=args.min_particles),
        region=region,
        engine=args.engine,
        particle_chunk=args.particles if args.chunk == 0 else args.chunk,
    )
    key = jax.random.key(0)
    round_index = strides.index(int(value)) if kind == "stride" else 0
    state = initial_state(key, args.particles, round_index, region, poses_gt[0])
    frames = frames_on_grid(seq, grid)
    frame_at = [jax.tree.map(lambda a, t=t: a[t], frames) for t in range(seq.num_frames)]
    active_at_start = int(jnp.sum(state.active))
    rss_before = peak_rss_mib()

    wall, cpu = time.perf_counter(), time.process_time()
    compiled = jax.jit(step).lower(key, state, frame_at[0], scene, config).compile()
    compile_wall, compile_cpu = time.perf_counter() - wall, time.process_time() - cpu

    walls, cpus, counts = [], [], []
    for t, frame in enumerate(frame_at):
        wall, cpu = time.perf_counter(), time.process_time()
        state, info = compiled(jax.random.key(100 + t), state, frame, scene, config)
        jax.block_until_ready((state, info))
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
        counts.append(int(info.num_particles))
    peak_rss = peak_rss_mib()  # the step's own peak, before the peer's arrays of rays
    peer_wall = peer_seconds(scene, np.asarray(state.poses), seq.camera, grid)
    return {
        "case": args.child,
        "rays_per_particle": int(grid.uv.shape[0]),
        "chunk": config.chunk_size(args.particles),
        "active_at_start": active_at_start,
        "compile_wall": compile_wall,
        "compile_cpu": compile_cpu,
        "frame_wall": walls,
        "frame_cpu": cpus,
        "num_particles": counts,
        "rss_before_mib": rss_before,
        "peak_rss_mib": peak_rss,
        "device_peak_mib": device_peak_mib(),
        "device": str(jax.devices()[0]),
        "peer_wall": peer_wall,
        "embree": describe_embree(args.engine),
    }


def peer_seconds(scene, poses, camera, grid) -> float:
    """Wall seconds (best of 2) single-threaded embreex (``EmbreeScene.run``) takes to cast every
    slot's rays of ``grid`` from ``poses`` (N, 4): what a step would cost in Embree alone if it
    rendered the whole capacity (the yardstick of the step's speed)."""
    import jax
    import numpy as np
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    from jaxloc.geometry import rotation_world_cam

    peer = rtcore_scene.EmbreeScene()
    triangles = np.asarray(scene.triangles)[: scene.num_triangles]
    TriangleMesh(peer, np.ascontiguousarray(triangles, np.float32))
    d_cam = np.asarray(camera.directions(grid.uv))
    rotations = np.asarray(jax.vmap(rotation_world_cam)(poses[:, 3]))
    directions = np.einsum("nij,rj->nri", rotations, d_cam).reshape(-1, 3).astype(np.float32)
    origins = np.repeat(poses[:, :3], d_cam.shape[0], axis=0).astype(np.float32)
    peer.run(origins[:1], directions[:1])  # builds its BVH
    best = np.inf
    for _ in range(2):
        start = time.perf_counter()
        peer.run(origins, directions)
        best = min(best, time.perf_counter() - start)
    return best


def describe_embree(engine: str) -> str:
    """Which Embree implementation the step's engine uses (or the engine's name)."""
    from jaxloc.raycasting import embree, resolve_engine

    return f"embree {embree.describe()}" if resolve_engine(engine) == "embree" else engine


# ----------------------------------------------------------------------------- report


def mean(values) -> float:
    return sum(values) / len(values)


def scale_to_full(args, rays: int, full_rays: int) -> float:
    """Linear scaling factor from this run's particles x rays to the full benchmark's."""
    return FULL_PARTICLES * full_rays / (args.particles * rays)


def full_rays(case: str) -> int:
    """Rays per particle of a case at 960x540."""
    import math

    if case.startswith("patch"):
        return 144
    stride = int(case.partition(":")[2].split()[0])
    width, height = FULL_SIZE
    return math.ceil((width - stride // 2) / stride) * math.ceil((height - stride // 2) / stride)


def total_row(args, results: list[dict], suffix: str, reduced: bool) -> list[str]:
    """The "all rounds" row of one tree's stride cases (none with fewer than two)."""
    stride_cases = [r for r in results if r["case"].startswith("stride")]
    if len(stride_cases) < 2:
        return []
    total = dict.fromkeys(("compile_wall", "compile_cpu", "wall", "cpu", "estimate", "peer"), 0.0)
    for result in stride_cases:
        frame_wall = mean(result["frame_wall"])
        total["compile_wall"] += result["compile_wall"]
        total["compile_cpu"] += result["compile_cpu"]
        total["wall"] += frame_wall
        total["cpu"] += mean(result["frame_cpu"])
        total["estimate"] += frame_wall * scale_to_full(
            args, result["rays_per_particle"], full_rays(result["case"])
        )
        total["peer"] += result["peer_wall"]
    row = [
        "all rounds (" + args.strides.replace(",", ", ") + ")" + suffix,
        "-",
        str(args.particles),
        f"{total['compile_wall']:.1f}",
        f"{total['compile_cpu']:.1f}",
        f"{total['wall']:.3f}",
        f"{total['cpu']:.3f}",
        f"{max(r['peak_rss_mib'] for r in stride_cases):.0f}",
        "-",
        f"{total['peer']:.3f}",
        f"{total['wall'] / total['peer']:.2f}",
    ]
    if reduced:
        row.append(f"{total['estimate']:.1f}")
    return ["| " + " | ".join(row) + " |"]


def report(args, data_info: dict, results: list[dict]) -> str:
    reduced = args.particles != FULL_PARTICLES or (args.width, args.height) != FULL_SIZE
    header = [
        "case",
        "rays/particle",
        "particles",
        "compile wall s",
        "compile CPU s",
        "s/frame wall",
        "s/frame CPU",
        "peak RSS MiB",
        "device peak MiB",
        "peer s (1-thread embreex, every slot's rays)",
        "step / peer (wall)",
    ]
    if reduced:
        header.append("ESTIMATE full size s/frame wall (linear scaling)")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for result in results:
        frame_wall, frame_cpu = mean(result["frame_wall"]), mean(result["frame_cpu"])
        estimate = frame_wall * scale_to_full(
            args, result["rays_per_particle"], full_rays(result["case"])
        )
        device_peak = result["device_peak_mib"]
        row = [
            result["case"].replace(":", " "),
            str(result["rays_per_particle"]),
            str(args.particles),
            f"{result['compile_wall']:.1f}",
            f"{result['compile_cpu']:.1f}",
            f"{frame_wall:.3f}",
            f"{frame_cpu:.3f}",
            f"{result['peak_rss_mib']:.0f}",
            "n/a" if device_peak is None else f"{device_peak:.0f}",
            f"{result['peer_wall']:.3f}",
            f"{frame_wall / result['peer_wall']:.2f}",
        ]
        if reduced:
            row.append(f"{estimate:.1f}")
        lines.append("| " + " | ".join(row) + " |")

    def label(result: dict) -> str:  # " (baseline)", " (depth-blind)", both, or ""
        return result["case"][len(result["case"].split(" ")[0]) :]

    for suffix in dict.fromkeys(label(r) for r in results):
        lines += total_row(args, [r for r in results if label(r) == suffix], suffix, reduced)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    notes = [
        "",
        f"engine {args.engine} ({results[0]['embree'] if results else '?'}); particles per "
        "render chunk: " + ", ".join(f"{r['case']} {r['chunk']}" for r in results),
        f"device: {results[0]['device'] if results else '?'}; {os.cpu_count()} CPUs; "
        f"load average {load}; python {platform.python_version()}",
        f"episode: seed {args.seed}, {args.frames} frames at {args.width}x{args.height}, room "
        f"{data_info['room']} m, {data_info['objects']} objects, {data_info['triangles']} "
        f"triangles (built in {data_info['seconds']:.1f} s)",
        "s/frame: mean over the frames of one compiled step (after compilation), blocking on "
        "the result; per-frame wall times: "
        + "; ".join(
            f"{r['case']}: " + ", ".join(f"{w:.2f}" for w in r["frame_wall"]) for r in results
        ),
        "particles active at the first frame (inactive slots cast no rays): "
        + ", ".join(f"{r['case']} {r['active_at_start']}" for r in results),
        "particles after each frame's KLD resampling (active at the next frame): "
        + "; ".join(
            f"{r['case']}: " + ", ".join(str(n) for n in r["num_particles"]) for r in results
        ),
        "peak RSS: ru_maxrss of the case's own process (includes the map, the sequence and the "
        "JAX runtime; RSS before compiling: "
        + ", ".join(f"{r['case']} {r['rss_before_mib']:.0f}" for r in results)
        + " MiB)",
    ]
    if reduced:
        notes.append(
            f"ESTIMATE column: wall s/frame scaled linearly by ({FULL_PARTICLES} particles x "
            "full-size rays) / (this run's particles x rays); an estimate, not a measurement."
        )
    return "\n".join(lines + notes)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.child is not None:
        print("RESULT " + json.dumps(run_case(args)), flush=True)
        return
    cases = []
    for case in args.cases.split(","):
        if case == "stride":
            cases += [f"stride:{int(s)}" for s in args.strides.split(",")]
        elif case == "patch":
            cases.append("patch:16x9")
        else:
            raise SystemExit(f"unknown case {case!r} (use 'stride' and/or 'patch')")
    with tempfile.TemporaryDirectory() as folder:
        data_info = make_data(args, Path(folder))
        print(f"episode built in {data_info['seconds']:.1f} s", flush=True)
        results = []
        trees = [None] if args.baseline is None else [None, args.baseline.resolve()]
        blind = [False, True] if args.depth_blind else [False]
        for case, tree, without in ((c, t, b) for c in cases for t in trees for b in blind):
            command = [sys.executable, __file__, "--child", case, "--data", folder]
            for name in ("particles", "frames", "width", "height", "strides", "seed", "engine"):
                command += [f"--{name}", str(getattr(args, name))]
            if args.chunk is not None:
                command += ["--chunk", str(args.chunk)]
            if args.min_particles is not None:
                command += ["--min-particles", str(args.min_particles)]
            if without:
                command.append("--without-depth")
            env = dict(os.environ)
            if tree is not None:
                env["PYTHONPATH"] = os.pathsep.join(
                    filter(None, [str(tree), env.get("PYTHONPATH")])
                )
            output = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
            lines = [x for x in output.stdout.splitlines() if x.startswith("RESULT ")]
            if output.returncode != 0 or not lines:
                sys.stderr.write(output.stderr[-4000:])
                raise SystemExit(f"case {case} failed (exit {output.returncode})")
            result = json.loads(lines[-1][len("RESULT ") :])
            if tree is not None:
                result["case"] += " (baseline)"
            if without:
                result["case"] += " (depth-blind)"
            results.append(result)
            print(
                f"{result['case']}: compile {result['compile_wall']:.1f} s, frames "
                + ", ".join(f"{w:.2f}" for w in result["frame_wall"])
                + " s",
                flush=True,
            )
    print()
    print(report(args, data_info, results))


if __name__ == "__main__":
    main()
