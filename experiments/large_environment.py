"""SG2Loc's large-environment experiment (appendix D, Table 11) at a reduced CPU scale.

Each environment merges ``--rooms`` synthetic rooms side by side into one scene graph
(:func:`jaxloc.synthetic.indoor.merge.merge_rooms`); a query sequence from every room is
localized with :func:`jaxloc.sg2loc.localize` twice at the same settings: with particles spread
over the whole merged floor (the large environment) and over its own room only (the usual
single-room case). Reported per setting: the fraction of sequences whose final MLE lies in the
correct room (SG2Loc's R^t@1 in Table 11), the final-frame pose errors and recalls, and for
comparison the sequential SceneGraphLoc retrieval (:mod:`jaxloc.sg2loc.retrieval`) of the correct
room among the environment's rooms.

Reduced scale (CPU, shared cores): 160x90 images, rooms with coarse 100-150-vertex meshes,
particle capacity 2000, two rounds at strides (8, 6) instead of the paper's 960x540, 863-vertex
meshes, 2500+ particles, strides (20, 8, 4), 50-frame sequences. Both settings share every
setting, seed and query, and every map is padded to one capacity (one compiled filter), so only
the map and the initialisation region (the map's floor bounding box) differ.

    JAX_PLATFORMS=cpu python experiments/large_environment.py --envs 2 --rooms 3 --frames 10
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from _atomic import write_text_atomic

from jaxloc.metrics import summarize, yaw_pose_errors
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc import KLDConfig, Region, SG2LocConfig, localize
from jaxloc.sg2loc.retrieval import Gallery, retrieve
from jaxloc.synthetic import indoor
from jaxloc.synthetic.indoor.merge import merge_rooms

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "large_environment"
ROOM = indoor.RoomConfig(vertex_range=(100, 150))
EPISODE = indoor.EpisodeConfig(room=ROOM, sensor=indoor.SensorConfig(width=160, height=90))
FIRST_SEED = 3000  # environment e, room r: seed FIRST_SEED + 10 e + r (tests use small seeds)


def run(args, command: str) -> list[dict]:
    """Localize every room's query in its merged environment and alone; rewrite the report after
    every sequence (so a run stopped early still leaves its results)."""
    config = SG2LocConfig(
        capacity=args.particles,
        strides=tuple(args.strides),
        box_half_widths=(0.8,) * (len(args.strides) - 1),
        kld=KLDConfig(min_particles=min(500, args.particles), max_particles=args.particles),
    )
    seeds = [[FIRST_SEED + 10 * e + r for r in range(args.rooms)] for e in range(args.envs)]
    # Rooms are cheap (make_room); build every map first and pad all of them (single rooms and
    # merged environments) to one capacity, so one compiled filter serves every run.
    rooms = [[indoor.make_room(seed, ROOM) for seed in env] for env in seeds]
    merged = [merge_rooms(env) for env in rooms]
    maps = [(m.meshes, m.labels, m.embeddings, m.colors) for m in merged]
    maps += [(r.meshes, r.labels, r.embeddings, r.colors) for env in rooms for r in env]
    exact = [SceneGraph.from_meshes(list(m[0]), *m[1:]) for m in maps]
    capacity = exact[0].capacity
    for scene in exact[1:]:
        capacity = capacity.union(scene.capacity)
    scenes = [SceneGraph.from_meshes(list(m[0]), *m[1:], capacity=capacity) for m in maps]
    merged_scenes, single_scenes = scenes[: args.envs], scenes[args.envs :]
    rows = []
    for e, env in enumerate(seeds):
        gallery = Gallery.from_embeddings([room.embeddings for room in rooms[e]])
        for r, seed in enumerate(env):
            episode = indoor.make_episode(seed, args.frames, EPISODE)
            assert np.array_equal(episode.room.embeddings, rooms[e][r].embeddings)
            retrieval = retrieve(episode.sequence.patch_embeddings, gallery)
            single = single_scenes[e * args.rooms + r]
            settings = {
                "single room": (single, Region.of_scene(single), episode.poses_gt),
                "merged": (
                    merged_scenes[e],
                    Region.of_scene(merged_scenes[e]),
                    merged[e].to_merged(episode.poses_gt, r),
                ),
            }
            for name, (scene, region, truth) in settings.items():
                start = time.perf_counter()
                result = localize(
                    jax.random.key(seed),
                    scene,
                    episode.sequence,
                    dataclasses.replace(config, region=region),
                )
                final = np.asarray(result.poses)[-1]
                seconds = time.perf_counter() - start
                pos, rot = yaw_pose_errors(final, truth[-1])
                if name == "merged":
                    room_found = int(merged[e].room_at(final[:2])) == r
                else:
                    size = np.asarray(rooms[e][r].size[:2])
                    room_found = bool(np.all((final[:2] >= 0) & (final[:2] <= size)))
                side = np.asarray(region.hi) - np.asarray(region.lo)
                rows.append(
                    {
                        "environment": e,
                        "room": r,
                        "seed": seed,
                        "setting": name,
                        "init_area_m2": float(side[0] * side[1]),
                        "map_mb": scene.storage_mb(),
                        "room_found": room_found,
                        "pos_err_m": float(pos),
                        "rot_err_deg": float(rot),
                        "seq_sgl_rank": int(np.flatnonzero(np.asarray(retrieval.ranking) == r)[0]),
                        "seconds": seconds,
                    }
                )
                print(rows[-1], flush=True)
                report(rows, args, command)
    return rows


def report(rows: list[dict], args, command: str) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Large environment (SG2Loc appendix D shape), reduced CPU scale",
        "",
        f"Command: `{command}`",
        "",
        f"{args.envs} environments of {args.rooms} merged rooms, one {args.frames}-frame query per "
        f"room ({len(rows) // 2} sequences), 160x90 images, capacity {args.particles}, strides "
        f"{tuple(args.strides)}. Errors are of the final frame's MLE. `room found` = the final "
        "MLE lies inside the query's room (Table 11's R^t@1 for SG2Loc); Seq. SGL R@1 = the "
        "sequential SceneGraphLoc score ranks the query's room first among the environment's "
        "rooms (the same queries). Timings are wall-clock on "
        f"{os.cpu_count()} CPU cores (load average {os.getloadavg()[0]:.2f} when the report was "
        "written); the first run (a single room) includes the filter's compilation.",
        "",
        "| setting | sequences | mean init area (m^2) | room found | Seq. SGL R@1 | mean pos (m) "
        "| mean rot (deg) | med pos (m) | med rot (deg) | R@10cm,5deg | R@25cm,10deg "
        "| s / sequence | map MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for setting in ("single room", "merged"):
        sub = [row for row in rows if row["setting"] == setting]
        if not sub:
            continue
        stats = summarize(
            np.array([row["pos_err_m"] for row in sub]),
            np.array([row["rot_err_deg"] for row in sub]),
        )
        lines.append(
            f"| {setting} | {len(sub)} | {np.mean([r['init_area_m2'] for r in sub]):.1f} "
            f"| {np.mean([r['room_found'] for r in sub]):.2f} "
            f"| {np.mean([r['seq_sgl_rank'] == 0 for r in sub]):.2f} "
            f"| {stats['mean_pos_m']:.2f} | {stats['mean_rot_deg']:.1f} "
            f"| {stats['median_pos_m']:.2f} | {stats['median_rot_deg']:.1f} "
            f"| {stats['R@0.1m,5deg']:.2f} | {stats['R@0.25m,10deg']:.2f} "
            f"| {np.mean([r['seconds'] for r in sub]):.0f} "
            f"| {np.mean([r['map_mb'] for r in sub]):.2f} |"
        )
    lines += [
        "",
        "Per sequence:",
        "",
        "| env | room | seed | setting | room found | pos (m) | rot (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['environment']} | {row['room']} | {row['seed']} | {row['setting']} "
            f"| {row['room_found']} | {row['pos_err_m']:.2f} | {row['rot_err_deg']:.1f} |"
        )
    write_text_atomic(OUT / "large_environment.md", "\n".join(lines) + "\n")
    fd, tmp = tempfile.mkstemp(prefix="large_environment.csv.", suffix=".tmp", dir=OUT)
    with os.fdopen(fd, "w", newline="") as f:
        f.write(f"# {command}\n")
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    os.chmod(tmp, 0o644)
    os.replace(tmp, OUT / "large_environment.csv")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--envs", type=int, default=2, help="merged environments")
    parser.add_argument("--rooms", type=int, default=3, help="rooms per environment")
    parser.add_argument("--frames", type=int, default=10, help="frames per query sequence")
    parser.add_argument("--particles", type=int, default=2000, help="particle capacity")
    parser.add_argument("--strides", type=int, nargs="+", default=[8, 6], help="round strides")
    args = parser.parse_args()
    command = "JAX_PLATFORMS=cpu python experiments/large_environment.py " + " ".join(sys.argv[1:])
    run(args, command)


if __name__ == "__main__":
    main()
