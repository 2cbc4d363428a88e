"""Run one ``jaxloc`` command in this process and write where its time went (for startup.py).

    python benchmarks/startup_probe.py OUT.json -- localize-lidar MAP SCAN ...

JAX reports every trace, lowering and XLA compilation (``jax.monitoring`` duration events; a
compilation answered by the persistent cache reports its load time as well). Nested programs are
traced inside their callers, so each kind is summed as the union of its intervals (wall time spent
in it, never counted twice). OUT.json holds, in wall seconds:

* ``import``: importing JAX and the command line;
* ``trace``, ``lower``, ``compile``, ``cache_load``: tracing, lowering to StableHLO, XLA
  compilation (less the cache loads), loading compiled programs from the persistent cache;
* ``rest``: the command's own time outside those (reading, computing, writing, Python);
* ``programs``, ``cache_hits``: compilations requested and answered by the cache;
* ``total``: the command, imports included; ``exit``: its exit code.
"""

from __future__ import annotations

import json
import sys
import time

START = time.perf_counter()

EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "backend",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache_load",
}


def union_seconds(intervals: list[tuple[float, float]]) -> float:
    """Total length of the union of (start, end) intervals."""
    total, reach = 0.0, -float("inf")
    for start, end in sorted(intervals):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


def main() -> None:
    out, argv = sys.argv[1], sys.argv[sys.argv.index("--") + 1 :]
    # the command line's own set-up before JAX is imported (here, to register the listeners)
    from jaxloc.cli import FAST_COMPILATION_COMMANDS
    from jaxloc.compilation_cache import prefer_fast_compilation

    if argv and argv[0] in FAST_COMPILATION_COMMANDS:
        prefer_fast_compilation()
    import jax

    intervals: dict[str, list[tuple[float, float]]] = {kind: [] for kind in EVENTS.values()}
    counts = {"programs": 0, "cache_hits": 0}

    def on_duration(event: str, duration: float, **kwargs) -> None:
        kind = EVENTS.get(event)
        if kind is not None:
            now = time.perf_counter()
            intervals[kind].append((now - duration, now))
        if event == "/jax/core/compile/backend_compile_duration":
            counts["programs"] += 1

    def on_event(event: str, **kwargs) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            counts["cache_hits"] += 1

    jax.monitoring.register_event_duration_secs_listener(on_duration)
    jax.monitoring.register_event_listener(on_event)
    from jaxloc.cli import main as jaxloc_main

    imported = time.perf_counter()
    code = jaxloc_main(argv)
    end = time.perf_counter()
    seconds = {kind: union_seconds(spans) for kind, spans in intervals.items()}
    compile_s = max(0.0, seconds.pop("backend") - seconds["cache_load"])
    jit_s = union_seconds([s for spans in intervals.values() for s in spans])
    report = {
        "import": imported - START,
        "trace": seconds["trace"],
        "lower": seconds["lower"],
        "compile": compile_s,
        "cache_load": seconds["cache_load"],
        "rest": max(0.0, end - imported - jit_s),
        **counts,
        "total": end - START,
        "exit": code,
    }
    with open(out, "w") as f:
        json.dump(report, f)
    sys.exit(code)


if __name__ == "__main__":
    main()
