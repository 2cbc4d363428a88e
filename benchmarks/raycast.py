"""Raycasting speed: jaxloc (render_batch / raycast, after compilation) vs trimesh + Embree
(``trimesh.ray.ray_pyembree.RayMeshIntersector.intersects_first``) on the SAME rays, same run.

Scene: a synthetic room of 40 objects (floor, ceiling, 4 walls, 34 pieces of furniture) of about
860 vertices each, ~65k triangles, like SG2Loc's coarse 3RScan meshes; built deterministically with
:mod:`jaxloc.synthetic.indoor`. Poses: random (x, y, z, yaw) inside the room. Ray sets:

* ``patch``: 16 x 9 patch grid, one ray per patch centre (:func:`jaxloc.patch_grid`), 144 rays/pose;
* ``stride``: every 20th pixel of 960 x 540 (:func:`jaxloc.stride_grid`), 48 x 27 = 1296 rays/pose.

Both wall time and process CPU time (``time.process_time``, all threads) are measured, since the
machine may be shared: rays per CPU-second is the fairer number there. The hit/miss + object
agreement between jaxloc and Embree is printed (target >= 99.9 %); a sample of disagreements is
adjudicated with a float64 brute force over all triangles.

    python benchmarks/raycast.py                 # 2500 poses, the paper's particle count
    python benchmarks/raycast.py --poses 100     # a quick run
    python benchmarks/raycast.py --baseline OLD_RAYCAST.py   # + an older traversal, same rays

``--baseline`` loads a module with a ``raycast(scene, origins, directions, packet_size=...)`` from
a file (e.g. an older ``jaxloc/raycasting/hits.py`` with its traversal pasted in) and times its
``raycast``; the file's imports resolve against the installed jaxloc, so it may import only what
exists there. Both cast the rays ``render_batch`` casts (tile order, packets of
:data:`jaxloc.sg2loc._rendering.PACKET_SIZE`), so the two traversals are compared side by side in
one run.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxloc
from jaxloc import raycasting
from jaxloc.geometry import rotation_world_cam
from jaxloc.raycasting.engines import resolve_engine
from jaxloc.sg2loc._rendering import PACKET_SIZE, _tiles
from jaxloc.synthetic.indoor import RoomConfig, make_room, scene_graph


def build_room(seed: int = 0):
    """The benchmark room: 6 structural objects + 34 furniture, 860 vertices each (host side)."""
    config = RoomConfig(
        length_range=(9.0, 10.0),
        width_range=(7.0, 8.0),
        num_objects=(34, 34),
        vertex_range=(860, 860),
    )
    room = make_room(seed, config)
    return room, scene_graph(room)


def random_poses(room, num: int, seed: int) -> np.ndarray:
    """(num, 4) float32 poses (x, y, z, yaw) inside the room, 0.3 m from the walls, z 1.2-1.8 m."""
    rng = np.random.default_rng(seed)
    lx, ly, _ = room.size
    return np.column_stack(
        [
            rng.uniform(0.3, lx - 0.3, num),
            rng.uniform(0.3, ly - 0.3, num),
            rng.uniform(1.2, 1.8, num),
            rng.uniform(-np.pi, np.pi, num),
        ]
    ).astype(np.float32)


def world_rays(poses: np.ndarray, camera: jaxloc.Camera, grid: jaxloc.RayGrid):
    """(N * R, 3) float32 origins and unit directions of every pose's grid rays (pose-major)."""
    d_cam = np.asarray(camera.directions(grid.uv))
    rot = np.asarray(jax.vmap(rotation_world_cam)(jnp.asarray(poses[:, 3])))
    d = np.einsum("nij,rj->nri", rot, d_cam).reshape(-1, 3)
    o = np.repeat(poses[:, :3], d_cam.shape[0], axis=0)
    return o.astype(np.float32), d.astype(np.float32)


def render_order_rays(
    poses, camera: jaxloc.Camera, grid: jaxloc.RayGrid, packet: int, engine: str = "jax"
):
    """The (N * R', 3) origins and directions ``render_batch`` casts with ``engine``: for "jax",
    tile order, padded to packets with NaN origins (R' = R rounded up to a multiple of
    ``packet``); for the others the grid's own order (R' = R)."""
    if resolve_engine(engine) != "jax":
        return world_rays(poses, camera, grid)
    order = _tiles(grid.shape)
    num = order.shape[0]
    padded = -(-num // packet) * packet
    o, d = world_rays(poses, camera, grid)
    d = np.pad(
        d.reshape(len(poses), num, 3)[:, order],
        ((0, 0), (0, padded - num), (0, 0)),
        constant_values=1.0,
    )
    o = np.broadcast_to(poses[:, None, :3], d.shape).copy()
    o[:, num:] = np.nan
    return o.reshape(-1, 3), d.reshape(-1, 3)


def load_module(path: str):
    """A raycast module loaded from a file (it imports ``jaxloc`` like the package's own)."""
    spec = importlib.util.spec_from_file_location("baseline_raycast", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # equinox's dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def timed(fn, repeats: int):
    """Best-of-``repeats`` (wall seconds, process CPU seconds) of ``fn()`` and its last result."""
    best = (np.inf, np.inf)
    out = None
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        w, c = time.perf_counter() - w0, time.process_time() - c0
        if w < best[0]:
            best = (w, c)
    return best[0], best[1], out


def brute_force_objects(triangles, tri_object, origins, directions):
    """Float64 nearest-hit object per ray over all triangles (slow: for a sample only)."""
    tris = np.asarray(triangles, np.float64)
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    out = np.full(len(origins), -1)
    for i in range(len(origins)):
        o, d = origins[i].astype(np.float64), directions[i].astype(np.float64)
        d = d / np.linalg.norm(d)
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - v0
            u = np.einsum("ij,ij->i", s, p) * inv
            q = np.cross(s, e1)
            v = (q @ d) * inv
            t = np.einsum("ij,ij->i", e2, q) * inv
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
        if ok.any():
            out[i] = tri_object[np.flatnonzero(ok)[np.argmin(t[ok])]]
    return out


def run_grid(name, scene, mesh_intersector, tri_object, poses, camera, grid, args):
    """Benchmark one ray set; returns a dict of numbers for the table."""
    num_rays = poses.shape[0] * grid.uv.shape[0]
    row = {"grid": name, "poses": poses.shape[0], "rays": num_rays}

    # jaxloc.render_batch: object, depth, colour, patch majority of every view.
    render = jax.jit(jaxloc.render_batch)
    w0 = time.perf_counter()
    compiled = render.lower(scene, poses, camera, grid).compile()
    row["render_compile_s"] = time.perf_counter() - w0
    wall, cpu, out = timed(
        lambda: jax.block_until_ready(compiled(scene, poses, camera, grid)), args.repeats
    )
    row["render_wall_s"], row["render_cpu_s"] = wall, cpu
    ours = np.asarray(out.object_id).reshape(-1)

    # The same rays through the render's raycast and through a baseline traversal (--baseline).
    if args.baseline:
        baseline = load_module(args.baseline)
        for key, module, packet in (
            ("new", raycasting, PACKET_SIZE),
            ("base", baseline, args.baseline_packet),
        ):
            o_tiles, d_tiles = render_order_rays(poses, camera, grid, packet)
            cast = jax.jit(functools.partial(module.raycast, packet_size=packet))
            w0 = time.perf_counter()
            compiled_cast = cast.lower(scene, o_tiles, d_tiles).compile()
            row[f"{key}_compile_s"] = time.perf_counter() - w0
            wall, cpu, hit = timed(
                lambda c=compiled_cast, o=o_tiles, d=d_tiles: jax.block_until_ready(c(scene, o, d)),
                args.repeats,
            )
            row[f"{key}_wall_s"], row[f"{key}_cpu_s"] = wall, cpu
            row[f"{key}_object"] = np.asarray(hit.object_id)[np.isfinite(o_tiles[:, 0])]
        row["base_agree"] = float(np.mean(row.pop("new_object") == row.pop("base_object")))

    # jaxloc.raycast on the flat rays (nearest hit only), packets of 1 (unrelated-ray traversal).
    origins, directions = world_rays(poses, camera, grid)
    if args.raycast:
        cast = jax.jit(functools.partial(jaxloc.raycast, packet_size=args.packet))
        w0 = time.perf_counter()
        compiled_cast = cast.lower(scene, origins, directions).compile()
        row["cast_compile_s"] = time.perf_counter() - w0
        wall, cpu, hit = timed(
            lambda: jax.block_until_ready(compiled_cast(scene, origins, directions)),
            args.repeats,
        )
        row["cast_wall_s"], row["cast_cpu_s"] = wall, cpu
        row["cast_vs_render_agree"] = float(np.mean(np.asarray(hit.object_id) == ours))

    # trimesh + Embree on the same rays.
    if mesh_intersector is not None:
        wall, cpu, tri = timed(
            lambda: mesh_intersector.intersects_first(origins, directions), args.repeats
        )
        row["embree_wall_s"], row["embree_cpu_s"] = wall, cpu
        theirs = np.where(tri >= 0, tri_object[np.maximum(tri, 0)], -1)
        disagree = np.flatnonzero(theirs != ours)
        row["agreement"] = 1.0 - disagree.size / num_rays
        sample = disagree[: args.adjudicate]
        if sample.size:
            ref = brute_force_objects(
                np.asarray(scene.triangles)[: scene.num_triangles],
                tri_object,
                origins[sample],
                directions[sample],
            )
            row["adjudicated"] = sample.size
            row["brute_sides_with_jaxloc"] = int(np.sum(ref == ours[sample]))
            row["brute_sides_with_embree"] = int(np.sum(ref == theirs[sample]))
    return row


def fmt_rate(rays, seconds):
    return f"{rays / seconds / 1e6:.3f}" if seconds and np.isfinite(seconds) else "-"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--poses",
        type=int,
        default=2500,
        help="poses per ray set (the paper's particle count: 2500)",
    )
    parser.add_argument("--grids", default="patch,stride", help="comma list of patch,stride")
    parser.add_argument("--repeats", type=int, default=2, help="timed runs (best of) per engine")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-raycast", dest="raycast", action="store_false", help="skip the raw raycast row"
    )
    parser.add_argument("--packet", type=int, default=1, help="packet_size of the raycast row")
    parser.add_argument("--no-embree", dest="embree", action="store_false")
    parser.add_argument(
        "--baseline", default=None, help="file of a module with an older raycast() to time beside"
    )
    parser.add_argument(
        "--baseline-packet", type=int, default=16, help="its packet size (16 before 4-wide)"
    )
    parser.add_argument(
        "--adjudicate", type=int, default=100, help="disagreements checked by brute force"
    )
    args = parser.parse_args(argv)

    t0 = time.perf_counter()
    room, scene = build_room(args.seed)
    build_s = time.perf_counter() - t0
    tri_object = np.asarray(scene.triangle_object)[: scene.num_triangles]
    vertices = sum(len(m.vertices) for m in room.meshes)
    intersector = None
    embree_build_s = float("nan")
    if args.embree:
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        tris = np.asarray(scene.triangles, np.float64)[: scene.num_triangles]
        mesh = trimesh.Trimesh(
            tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3), process=False
        )
        intersector = RayMeshIntersector(mesh)
        t0 = time.perf_counter()
        intersector.intersects_first(np.zeros((1, 3)), np.ones((1, 3)))  # builds Embree's BVH
        embree_build_s = time.perf_counter() - t0

    camera = jaxloc.Camera.from_fov(960, 540, 60.0)
    grids = {"patch": jaxloc.patch_grid(camera, 9, 16), "stride": jaxloc.stride_grid(camera, 20)}
    poses = random_poses(room, args.poses, args.seed + 1)

    print("# jaxloc raycast benchmark")
    print(
        f"\n- scene: {scene.num_objects} objects, {vertices} vertices "
        f"({vertices / scene.num_objects:.0f}/object), {scene.num_triangles} triangles, "
        f"{scene.capacity.leaves} BVH leaves; map {scene.storage_mb():.2f} MB"
    )
    print(
        f"- host build (room + SceneGraph + BVH): {build_s:.1f} s; "
        f"Embree build {embree_build_s:.3f} s"
    )
    print(
        f"- jax {jax.__version__} on {jax.devices()[0].platform} ({jax.devices()[0].device_kind}), "
        f"{os.cpu_count()} CPUs visible, {platform.processor() or platform.machine()}; "
        f"load average {os.getloadavg()[0]:.1f} at the start"
    )
    rows = [
        run_grid(name, scene, intersector, tri_object, poses, camera, grids[name], args)
        for name in args.grids.split(",")
    ]

    print(
        "\n| rays | engine | compile s | wall s | CPU s | M rays/s (wall) | M rays/CPU-s "
        "| vs Embree (wall) | vs Embree (CPU) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        label = f"{r['grid']}: {r['poses']} x {r['rays'] // r['poses']} = {r['rays']}"
        engines = [("jaxloc render_batch", "render")]
        if "new_wall_s" in r:
            engines.append((f"jaxloc raycast, render's rays (packet {PACKET_SIZE})", "new"))
            engines.append((f"baseline raycast, same rays (packet {args.baseline_packet})", "base"))
        if "cast_wall_s" in r:
            engines.append((f"jaxloc raycast (packet {args.packet})", "cast"))
        if "embree_wall_s" in r:
            engines.append(("trimesh + Embree", "embree"))
        for title, key in engines:
            wall, cpu = r[f"{key}_wall_s"], r[f"{key}_cpu_s"]
            compile_s = r.get(f"{key}_compile_s")
            ratio_w = ratio_c = "-"
            if "embree_wall_s" in r and key != "embree":
                ratio_w = f"{r['embree_wall_s'] / wall:.3f}x"
                ratio_c = f"{r['embree_cpu_s'] / cpu:.3f}x"
            compiled = "-" if compile_s is None else f"{compile_s:.1f}"
            rates = f"{fmt_rate(r['rays'], wall)} | {fmt_rate(r['rays'], cpu)}"
            print(
                f"| {label} | {title} | {compiled} | {wall:.3f} | {cpu:.3f} | {rates} "
                f"| {ratio_w} | {ratio_c} |"
            )
    print(f"\n- load average {os.getloadavg()[0]:.1f} at the end")
    for r in rows:
        if "agreement" in r:
            line = (
                f"- {r['grid']}: jaxloc vs Embree same hit/miss and object on "
                f"{100 * r['agreement']:.3f} % of {r['rays']} rays"
            )
            if r.get("adjudicated"):
                line += (
                    f"; of {r['adjudicated']} disagreements checked by float64 brute force, it "
                    f"sides with jaxloc on {r['brute_sides_with_jaxloc']} and with Embree on "
                    f"{r['brute_sides_with_embree']}"
                )
            print(line)
        if "base_agree" in r:
            print(
                f"- {r['grid']}: baseline vs jaxloc raycast same object on "
                f"{100 * r['base_agree']:.3f} % of rays"
            )
        if "cast_vs_render_agree" in r:
            print(
                f"- {r['grid']}: raycast vs render_batch same object on "
                f"{100 * r['cast_vs_render_agree']:.3f} % of rays"
            )


if __name__ == "__main__":
    main()
