"""Nearest-hit engines side by side: ``jaxloc.raycast`` and ``jaxloc.render_batch`` with every
installed engine vs single-threaded Embree (embreex ``EmbreeScene.run``, the peer) on the same rays,
same run, reported as ratios of wall time (what a user waits for); process CPU time stands beside.

Scene and rays are those of ``benchmarks/raycast.py``: the synthetic benchmark room (40 objects,
~60k triangles) and 2500 random poses, with two ray sets per pose:

* ``stride``: every 20th pixel of 960 x 540 (48 x 27 = 1296 rays), SG2Loc's coarse pass;
* ``stride-tiles``: the same rays, each pose's 4 x 4 tile by tile (coherent packets);
* ``patch``: one ray per 16 x 9 patch centre (144 rays).

``raycast`` rows cast the flat, pose-major rays (nearest hit only; ``t``, barycentric coordinates
and object computed by JAX); ``render_batch`` rows render the views as the filter does (tile order,
depth, colour, patch majority). With the native Embree engine, two ``native handler alone`` rows
time its FFI call by itself on rays made ready beforehand (faces only; with t, u, v), which
splits ``raycast``'s time into the call and JAX's passes around it. The peer gets the same flat
rays in one ``run`` call (one thread). Agreement is the share of rays whose hit triangle equals
the peer's.

    python benchmarks/engines.py                        # 2500 poses, both ray sets
    python benchmarks/engines.py --poses 200 --grids stride
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import platform
import resource
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from raycast import build_room, random_poses, timed, world_rays  # noqa: E402

import jaxloc  # noqa: E402
from jaxloc.raycasting import _native, embree, engines
from jaxloc.sg2loc._rendering import _tiles  # noqa: E402


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10


def minor_faults() -> int:
    """Minor page faults of this process so far: first touches of fresh memory, e.g. XLA's
    output buffers where the C library hands back freshly mapped pages (a call's own cost)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def device_peak_mib():
    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 - backends without memory statistics
        return None
    return None if not stats else stats.get("peak_bytes_in_use", 0) / 2**20


def compiled_call(fn, args):
    """(compile wall s, a no-argument call of the compiled ``jax.jit(fn)`` that blocks). The
    arguments go to the device once, so a call times the program, not copying numpy arrays in."""
    args = jax.device_put(args)
    w0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - w0
    call = lambda: jax.block_until_ready(compiled(*args))  # noqa: E731
    call()  # first call: builds and caches the engine's structure for this map
    return compile_s, call


@contextlib.contextmanager
def python_embree():
    """Trace the Embree engine's calls to its Python implementation (embreex from a Python FFI
    target, today's fallback) instead of the native one, in this block."""
    native_target = embree._target
    embree._target = embree.python_target
    try:
        yield
    finally:
        embree._target = native_target


def with_packet_width(call, width):
    """``call`` with the native engine's packets set to ``width`` rays (1: single rays only),
    restored afterwards."""
    engine = _native.load()

    def run():
        before = engine.packet_width
        engine.set_packet_width(width)
        try:
            return call()
        finally:
            engine.set_packet_width(before)

    return run


def variants(names):
    """(label, raycast keyword arguments, python implementation?, packet width or None) rows."""
    rows = []
    native = embree.implementation() == "native"
    for engine in names:
        rows.append((f"raycast, engine={engine}", {"engine": engine}, False, None))
        if engine != "jax":
            rows.append(
                (f"raycast, engine={engine}, differentiable=False",
                 {"engine": engine, "differentiable": False}, False, None)
            )  # fmt: skip
    if native and "embree" in names:
        for kwargs, label in (({}, ""), ({"differentiable": False}, ", differentiable=False")):
            kwargs = {"engine": "embree", **kwargs}
            rows.append((f"raycast, embree native, single rays{label}", kwargs, False, 1))
            rows.append((f"raycast, embree Python fallback{label}", kwargs, True, None))
    return rows


def handler_rows(scene, origins, directions):
    """The native handler's FFI call alone, on rays made ready beforehand (unit directions, all
    valid), faces only and with the t, u, v of ``differentiable=False``: what ``raycast``'s own
    JAX passes around the call cost, and what the exact values inside it cost."""
    unit = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    args = (scene.triangles, origins, unit.astype(np.float32), np.ones(origins.shape[0], bool))
    rows = []
    for label, search in (("faces only", embree.nearest_triangle), ("t, u, v", embree.nearest_hit)):
        compile_s, call = compiled_call(search, args)
        rows.append({"what": f"native handler alone ({label})", "compile": compile_s, "call": call})
    return rows


def run_grid(scene, peer, poses, camera, grid, names, repeats, tiles=False):
    """Every row of one ray set, timed round-robin (``repeats`` rounds, best of each row), so no
    row is favoured by running first or last. ``tiles``: each pose's rays 4 x 4 tile by tile (as
    the filter casts a camera's rays for packet engines) instead of row by row."""
    origins, directions = world_rays(poses, camera, grid)
    if tiles:
        order = _tiles(grid.shape)
        num = order.shape[0]
        origins = origins.reshape(-1, num, 3)[:, order].reshape(-1, 3)
        directions = directions.reshape(-1, num, 3)[:, order].reshape(-1, 3)
    rows = [{"what": "embreex EmbreeScene.run, 1 thread (peer)", "call": None}]
    rows[0]["call"] = lambda: peer.run(origins, directions)
    for label, kwargs, python, width in variants(names):
        cast = functools.partial(jaxloc.raycast, **kwargs)
        with python_embree() if python else contextlib.nullcontext():
            compile_s, call = compiled_call(cast, (scene, origins, directions))
        if width is not None:
            call = with_packet_width(call, width)
        rows.append({"what": label, "compile": compile_s, "call": call})
    if embree.implementation() == "native" and "embree" in names:
        rows += handler_rows(scene, origins, directions)
    for engine in names:
        render = functools.partial(jaxloc.render_batch, engine=engine)
        compile_s, call = compiled_call(render, (scene, poses, camera, grid))
        rows.append({"what": f"render_batch, engine={engine}", "compile": compile_s, "call": call})
    peer_triangles = rows[0]["call"]()
    for row in rows:
        row["wall"], row["cpu"] = np.inf, np.inf
    for _ in range(repeats):
        for row in rows:
            faults = minor_faults()
            wall, cpu, out = timed(row["call"], 1)
            if wall < row["wall"]:
                row["wall"], row["cpu"] = wall, cpu
                row["faults"] = minor_faults() - faults
            if row["what"].startswith("raycast"):
                row["agree"] = float(np.mean(np.asarray(out.triangle_id) == peer_triangles))
    for row in rows:
        row["ratio"] = rows[0]["wall"] / row["wall"]
    return origins.shape[0], rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=2500)
    parser.add_argument(
        "--grids", default="stride,stride-tiles,patch", help="comma list of those ray sets"
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed runs (best of) per row")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--engines", default=None, help="comma list (default: auto and every installed engine)"
    )
    args = parser.parse_args(argv)
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    names = (
        args.engines.split(",")
        if args.engines
        else ["auto", "jax"] + [e for e in ("embree", "warp") if engines.is_installed(e)]
    )
    t0 = time.perf_counter()
    room, scene = build_room(args.seed)
    build_s = time.perf_counter() - t0
    triangles = np.asarray(scene.triangles)[: scene.num_triangles]
    t0 = time.perf_counter()
    peer = rtcore_scene.EmbreeScene()
    TriangleMesh(peer, np.ascontiguousarray(triangles))
    peer.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # builds its BVH
    peer_build_s = time.perf_counter() - t0
    camera = jaxloc.Camera.from_fov(960, 540, 60.0)
    stride = jaxloc.stride_grid(camera, 20)
    grids = {"patch": jaxloc.patch_grid(camera, 9, 16), "stride": stride, "stride-tiles": stride}
    poses = random_poses(room, args.poses, args.seed + 1)
    load_start = os.getloadavg()[0]
    device = jax.devices()[0]

    print("# jaxloc nearest-hit engines vs single-threaded Embree")
    print(
        f"\n- scene: {scene.num_objects} objects, {scene.num_triangles} triangles; host build "
        f"{build_s:.1f} s; peer Embree build {peer_build_s:.3f} s"
    )
    print(
        f"- jax {jax.__version__} on {device.platform} ({device.device_kind}); "
        f"{os.cpu_count()} CPUs visible, {platform.processor() or platform.machine()}; "
        f"auto = {engines.resolve_engine('auto')}; Embree engine: {embree.describe()}"
    )
    print(f"- load average {load_start:.1f} at the start")
    print(
        "\n| rays | what | compile s | wall s | CPU s | page faults | M rays/s (wall) "
        "| vs peer (wall) | same triangle as peer |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.grids.split(","):
        num_rays, rows = run_grid(
            scene, peer, poses, camera, grids[name], names, args.repeats, name.endswith("tiles")
        )
        label = f"{name}: {args.poses} x {num_rays // args.poses} = {num_rays}"
        for row in rows:
            compile_s = f"{row['compile']:.1f}" if "compile" in row else "-"
            agree = f"{100 * row['agree']:.3f} %" if "agree" in row else "-"
            print(
                f"| {label} | {row['what']} | {compile_s} | {row['wall']:.3f} | {row['cpu']:.3f} "
                f"| {row['faults']} | {num_rays / row['wall'] / 1e6:.2f} | {row['ratio']:.2f}x "
                f"| {agree} |"
            )
    device_peak = device_peak_mib()
    print(
        f"\n- load average {os.getloadavg()[0]:.1f} at the end; peak RSS of the process "
        f"{peak_rss_mib():.0f} MiB"
        + ("" if device_peak is None else f"; peak device memory {device_peak:.0f} MiB")
    )
    print(
        "- wall s: best of the timed runs after compilation and a warm-up call (which builds "
        "the engine's acceleration structure once per map), the rows timed in turn in each "
        "round; page faults: the process's minor faults in that run; render_batch rows "
        "include the views (depth, colour, patch majority), so their ratio is against the "
        "peer's bare raycast"
    )


if __name__ == "__main__":
    main()
