"""Where one SG2Loc filter step's time goes, measured inside the compiled step (XLA:CPU trace).

``benchmarks/filter_profile.py`` times each part as a program of its own; fused into the step the
parts cost less (its "rest" row goes negative). This script runs the compiled step itself under
``jax.profiler.trace`` and attributes every XLA operation the trace records to the part of the step
it belongs to, by the named scopes the library sets (``jax.named_scope``: ``rays``, ``ray_prep``,
``hit_search``, ``hit_values``, ``views``, ``color_score``, ...; an operation XLA fused from several
scopes counts for the scope of its root). Per part it reports

the wall time during which one of its operations ran (the union of their intervals over the
threads), per step. An operation is one event however many threads work on it (XLA splits a large
loop over its thread pool, the engine's FFI call casts on its own native threads as well), so the
parts' walls add up to the step's, less ``idle``: the step's traced wall minus the union of every
part (thunk scheduling, loop control, waits). The episode is ``filter_step.py``'s (3 frames);
each stride starts from its round's particles and is timed on frame 1, after a step on frame 0.

    python benchmarks/step_trace.py                 # strides 20, 8, 4
    python benchmarks/step_trace.py --strides 4 --repeats 5
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from filter_profile import add_step_arguments, stepped_state  # noqa: E402
from filter_step import load_data, make_data  # noqa: E402

from jaxloc.raycasting.engines import resolve_engine  # noqa: E402

#: (named scope, part) in the order they are looked for: an operation belongs to the first scope
#: found in its name path (scopes nest: ``score`` holds the others of the chunk loop).
PARTS = (
    ("hit_search", "hit search (the engine's call)"),
    ("ray_prep", "ray normalisation and validity (raycast)"),
    ("hit_values", "hit values (object, masks, barycentric)"),
    ("rays", "ray directions (rotation to the world)"),
    ("views", "views (depth, colour, patch majority)"),
    ("color_score", "colour score (SSIM)"),
    ("depth_score", "depth score"),
    ("semantic_score", "semantic score"),
    ("predict", "prediction (motion model)"),
    ("match", "patch matching"),
    ("update", "weights, estimates, verdict, KLD resampling, injection"),
    ("score", "chunk loop (gathers, slices, score bookkeeping)"),
)
OTHER = "other (no scope)"
#: The strides of the paper's coarse-to-fine rounds, in order.
PAPER_STRIDES = (20, 8, 4)
_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%(\S+) = .*?\s([a-z][\w-]*)\(.*op_name=\"([^\"]*)\"")
#: Operations whose trace events stand for others (their bodies run as operations of their own).
_CONTAINERS = {"while", "conditional", "call"}


def part_of(op_name: str) -> str:
    """The part (see :data:`PARTS`) of an operation by its ``op_name`` metadata."""
    components = op_name.split("/")
    for scope, part in PARTS:
        if any(c == scope or c.endswith(f"({scope})") for c in components):
            return part
    return OTHER


def operation_parts(hlo_text: str) -> dict[str, str]:
    """Part of each operation (instruction name) of a compiled program's HLO text, leaving out
    the operations that only hold others (while loops, conditionals, calls)."""
    parts = {}
    for line in hlo_text.splitlines():
        found = _INSTRUCTION.match(line)
        if found and found.group(2) not in _CONTAINERS:
            parts[found.group(1)] = part_of(found.group(3))
    return parts


def union_length(intervals: list[tuple[int, int]]) -> int:
    """Total length covered by (start, end) intervals."""
    total, reach = 0, None
    for start, end in sorted(intervals):
        if reach is None or start > reach:
            total += end - start
            reach = end
        elif end > reach:
            total += end - reach
            reach = end
    return total


def attribute(trace_file: Path, parts: dict[str, str], runs: int) -> tuple[dict, dict]:
    """From an XLA:CPU trace of ``runs`` steps, per step: (wall s, operations) of each part and
    of "all" (the union of every part), and the wall s of each operation (by name)."""
    intervals: dict[str, list] = {}
    counts: dict[str, int] = {}
    operations: dict[str, list] = {}
    profile = jax.profiler.ProfileData.from_file(str(trace_file))
    for plane in profile.planes:
        for line in plane.lines:
            for event in line.events:
                part = parts.get(event.name)
                if part is None:
                    continue
                span = (int(event.start_ns), int(event.end_ns))
                operations.setdefault(event.name, []).append(span)
                for key in (part, "all"):
                    intervals.setdefault(key, []).append(span)
                    counts[key] = counts.get(key, 0) + 1
    by_part = {
        key: (union_length(spans) * 1e-9 / runs, counts[key] // runs)
        for key, spans in intervals.items()
    }
    by_operation = {name: union_length(spans) * 1e-9 / runs for name, spans in operations.items()}
    return by_part, by_operation


def trace_stride(scene, seq, poses_gt, stride: int, round_index: int, args) -> dict:
    config, compiled, state, frame1 = stepped_state(scene, seq, poses_gt, stride, round_index, args)

    def run():
        start = time.perf_counter()
        jax.block_until_ready(compiled(jax.random.key(2), state, frame1, scene, config))
        return time.perf_counter() - start

    run()
    untraced = [run() for _ in range(args.repeats)]
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            traced = [run() for _ in range(args.traced)]
        trace_file = next(Path(folder).rglob("*.xplane.pb"))
        names = operation_parts(compiled.as_text())
        parts, operations = attribute(trace_file, names, args.traced)
    heaviest = sorted(operations.items(), key=lambda item: -item[1])[: args.top]
    return {
        "stride": stride,
        "rays": int(config.grid.uv.shape[0]),
        "active": int(np.sum(np.asarray(state.active))),
        "untraced": untraced,
        "traced": statistics.mean(traced),
        "parts": parts,
        "heaviest": [(name, names[name], wall) for name, wall in heaviest],
    }


def report(args, info: dict, load: tuple[float, float], results: list[dict]) -> str:
    device = jax.devices()[0]
    lines = [
        f"# Filter step, traced ({args.width}x{args.height}, {args.particles} particles, engine "
        f"{args.engine} = {resolve_engine(args.engine)})\n",
        f"- {device.platform} ({device.device_kind}), {os.cpu_count()} CPUs; load average "
        f"{load[0]:.1f} at the start, {load[1]:.1f} at the end; room of {info['objects']} "
        f"objects, {info['triangles']} triangles",
    ]
    for r in results:
        steps = sorted(r["untraced"])
        wall = r["traced"]
        search = r["parts"].get(PARTS[0][1])
        rays = r["active"] * r["rays"]
        lines += [
            f"\n## stride {r['stride']}: {r['rays']} rays per particle, {r['active']} active "
            f"({rays / 1e6:.1f} M rays a step)\n",
            f"Step wall: best {steps[0]:.3f} s, median {statistics.median(steps):.3f} s "
            f"untraced ({len(steps)} runs); {wall:.3f} s traced (mean of {args.traced}).",
        ]
        if search is not None and search[0] > 0:
            lines.append(f"Hit search: {rays / search[0] / 1e6:.1f} M rays/s over its wall.")
        lines += ["", "| part | wall s | % of the step | operations |", "|---|---|---|---|"]
        ordered = [p for _, p in PARTS] + [OTHER]
        for part in ordered:
            if part in r["parts"]:
                w, n = r["parts"][part]
                lines.append(f"| {part} | {w:.3f} | {100 * w / wall:.0f} % | {n} |")
        covered = r["parts"].get("all", (0.0, 0))[0]
        lines.append(
            f"| idle (no operation running) | {wall - covered:.3f} | "
            f"{100 * (wall - covered) / wall:.0f} % | - |"
        )
        if r["heaviest"]:
            lines += ["", "| operation | part | wall s |", "|---|---|---|"]
            lines += [f"| `{n}` | {part} | {w:.3f} |" for n, part, w in r["heaviest"]]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_step_arguments(parser)
    parser.add_argument("--repeats", type=int, default=5, help="untraced steps timed")
    parser.add_argument("--traced", type=int, default=2, help="steps traced")
    parser.add_argument("--top", type=int, default=0, help="list the heaviest operations")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if jax.default_backend() != "cpu":
        parser.error("the trace is attributed for XLA:CPU only; use filter_profile.py elsewhere")
    args.frames = 3  # the episode of filter_step.py, whose frame 1 the step is timed on
    with tempfile.TemporaryDirectory() as folder:
        info = make_data(args, Path(folder))
        scene, seq, poses_gt = load_data(Path(folder), args.width, args.height)
    start_load = os.getloadavg()[0]
    strides = [int(s) for s in args.strides.split(",")]
    # A stride of the paper's rounds starts from that round's particles, whatever else is asked.
    rounds = [PAPER_STRIDES.index(s) if s in PAPER_STRIDES else i for i, s in enumerate(strides)]
    results = [
        trace_stride(scene, seq, poses_gt, s, r, args) for s, r in zip(strides, rounds, strict=True)
    ]
    print(report(args, info, (start_load, os.getloadavg()[0]), results))


if __name__ == "__main__":
    main()
