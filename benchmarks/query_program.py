"""The M2Loc query program: its first call (tracing + compilation) and its query time, per map.

For each real HeLiPR map: describe it with M2Loc's default configuration (``m2loc_config(3)``,
robust), time the first ``localize_scan`` (the query programs traced and compiled, no persistent
cache), then the median and p90 of the match + clique + pose time over seeded scan-like queries
(after compilation). One JSON line per map on stdout, so two versions of jaxloc can be run side by
side on the same queries (``PYTHONPATH=<other checkout>``) and compared in one sitting:

    python benchmarks/query_program.py --queries 40 [--maps KAIST04 DCC04] [--label new]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import numpy as np  # noqa: E402

import jaxloc  # noqa: E402
from jaxloc.io import read_instance_map, read_road_normals  # noqa: E402
from jaxloc.m2loc import build_map, localize_scan, m2loc_config, pad_scan  # noqa: E402
from jaxloc.synthetic.outdoor import make_query  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "helipr_instance_maps"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--queries", type=int, default=40)
    parser.add_argument("--maps", nargs="*", default=None, help="map names (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--label", default="", help="a name for this run's lines")
    args = parser.parse_args()
    config = m2loc_config(3)
    for name in args.maps or sorted(p.name for p in DATA.iterdir()):
        instances = read_instance_map(DATA / name)
        normals = read_road_normals(DATA / name)
        triplet_map = build_map(instances.points, instances.labels, config, normals)
        rng = np.random.default_rng(args.seed)
        queries = [
            make_query(instances.points, instances.labels, normals, rng, max_kept=25)
            for _ in range(args.queries)
        ]
        first_seconds = {}
        for q in queries:  # the first query of each capacity traces and compiles its programs
            capacity = len(pad_scan(q.points, q.labels, triplet_map.config)[0])
            if capacity not in first_seconds:
                start = time.perf_counter()
                localize_scan(triplet_map, None, q.points, q.labels)
                first_seconds[capacity] = time.perf_counter() - start
        match_ms, valid = [], []
        for q in queries:
            result = localize_scan(triplet_map, None, q.points, q.labels)
            match_ms.append(result.match_time_ms)
            valid.append(result.valid)
        print(
            json.dumps(
                {
                    "label": args.label,
                    "jaxloc": str(Path(jaxloc.__file__).parent),
                    "map": name,
                    "first_call_s": {str(k): round(v, 2) for k, v in first_seconds.items()},
                    "query_ms_median": round(statistics.median(match_ms), 2),
                    "query_ms_p90": round(float(np.percentile(match_ms, 90)), 2),
                    "valid": int(sum(valid)),
                    "queries": len(queries),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
