"""The shape of SG2Loc's Table 5: sequential scene retrieval on synthetic indoor scenes.

A pool of synthetic rooms (``jaxloc.synthetic.indoor``; every room shares the class vectors of
``RoomConfig.class_seed = 0``, so objects of one class look alike across rooms): ``--queries``
rooms with a ``--frames``-frame query episode from :func:`make_episode` (their patch embeddings
carry the dataset's confusions and noise) and ``--distractors`` rooms from :func:`make_room`.
Each query episode is cut into non-overlapping windows of 1, 5, 10, 25 and 50 frames; each
window is retrieved among 10 and among 50 candidates (its own room plus 9 / 49 other pool rooms
drawn at random, ``--draws`` draws per window) with :func:`jaxloc.sg2loc.retrieval.retrieve`'s
scores; R@1/3/5 average over windows and draws. A window's score is the sum of its frames' scores,
so every frame is scored once against the whole pool (checked against a direct ``retrieve`` call).

Difficulty: with the dataset's own patch embeddings every patch is a noisy copy of an object
of the true room, and retrieval saturates (R@1 = 1 from one frame). Exploratory runs (ad hoc,
summarised at the end of results/retrieval/table5.md) showed it stays saturated when the
rooms' embeddings are redrawn with class similarity up to 0.95, patch cosines down to 0.2-0.5
or a per-object query/map appearance gap. What breaks it is patches attributed to objects that
are NOT in the room: the two harder rows replace 50 % / 70 % of the patches by embeddings of
new objects of random classes (:func:`query_patches`). These rates were chosen after one sweep
that saw only 1- and 10-frame R@1 at 80 % and 90 % (both ~0); all three rows are reported.

Time per query: median wall time of :func:`jaxloc.sg2loc.retrieval.retrieve` after compilation (the
public call, validation included) on the 2 shared CPU cores; storage: the float32 object
embeddings a scene contributes to the database (:meth:`Gallery.storage_mb`).

    JAX_PLATFORMS=cpu python experiments/retrieval_table5.py --queries 8 --distractors 46 \
        --frames 100
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
from _atomic import write_text_atomic

from jaxloc.sg2loc.retrieval import Gallery, recall_at_k, retrieve, true_rank
from jaxloc.synthetic import indoor

LENGTHS = (1, 5, 10, 25, 50)
CANDIDATES = (10, 50)
KS = (1, 3, 5)
ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "retrieval"
#: Coarse meshes (100-150 vertices per object): retrieval only needs which object each patch
#: sees, and the BVH build inside the query renderer is ~6x faster than at 400-1000 vertices.
ROOM = indoor.RoomConfig(vertex_range=(100, 150))
SENSOR = indoor.SensorConfig(width=160, height=90)
EPISODE = indoor.EpisodeConfig(room=ROOM, sensor=SENSOR)


def _atomic_savez(path: Path, **arrays) -> None:
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "wb") as f:
        np.savez(f, **arrays)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def generate(cache: Path, query_seeds, distractor_seeds, num_frames: int) -> None:
    """Write one npz per room: labels, embeddings and (for query rooms) the episode's patches."""
    cache.mkdir(parents=True, exist_ok=True)
    for seed in query_seeds:
        path = cache / f"episode_{seed}.npz"
        if path.exists():
            continue
        start = time.perf_counter()
        try:
            episode = indoor.make_episode(seed, num_frames, EPISODE)
        except RuntimeError as err:  # no trajectory fits the room: recorded, seed skipped
            print(f"seed {seed}: skipped ({err})", flush=True)
            continue
        _atomic_savez(
            path,
            labels=episode.room.labels,
            embeddings=episode.room.embeddings,
            patch_embeddings=np.asarray(episode.sequence.patch_embeddings),
            patch_objects=episode.patch_objects,
            confused=episode.confused,
        )
        print(f"episode {seed}: {time.perf_counter() - start:.1f} s", flush=True)
    for seed in distractor_seeds:
        path = cache / f"room_{seed}.npz"
        if path.exists():
            continue
        start = time.perf_counter()
        room = indoor.make_room(seed, ROOM)
        _atomic_savez(path, labels=room.labels, embeddings=room.embeddings)
        print(f"room {seed}: {time.perf_counter() - start:.1f} s", flush=True)


@dataclass(frozen=True)
class Difficulty:
    """How a query's patch embeddings are corrupted on top of the dataset's own."""

    name: str
    misrecognition_rate: float = 0.0


DIFFICULTIES = (
    Difficulty("dataset default (make_episode's patches as generated)"),
    Difficulty("50% of patches misrecognised", 0.5),
    Difficulty("70% of patches misrecognised", 0.7),
)


def load_pool(cache: Path, query_seeds, distractor_seeds):
    """Rooms (seed, labels, embeddings) and query episodes (index into rooms, npz arrays)."""
    rooms, queries = [], []
    for seed in query_seeds:
        path = cache / f"episode_{seed}.npz"
        if path.exists():
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
            queries.append((len(rooms), arrays))
            rooms.append((seed, arrays["labels"], arrays["embeddings"]))
    for seed in distractor_seeds:
        with np.load(cache / f"room_{seed}.npz", allow_pickle=False) as data:
            rooms.append((seed, data["labels"], data["embeddings"]))
    return rooms, queries


def query_patches(difficulty: Difficulty, seed: int, patches: np.ndarray) -> np.ndarray:
    """(T, rows, cols, d) patches with ``misrecognition_rate`` of them replaced by the embedding
    of a new object of a uniformly random class (``indoor.object_embeddings`` with the dataset's
    class vectors), i.e. a patch the encoder attributes to an object that need not be in the
    room."""
    if difficulty.misrecognition_rate == 0:
        return patches
    rng = np.random.default_rng([seed, 2])
    wrong = rng.uniform(size=patches.shape[:-1]) < difficulty.misrecognition_rate
    labels = rng.integers(0, len(indoor.CLASS_NAMES), size=int(wrong.sum()))
    out = patches.copy()
    out[wrong] = indoor.object_embeddings(labels, rng, patches.shape[-1])
    return out


def evaluate(difficulty, rooms, queries, draws: int, seed: int):
    """Recall rows {length, candidates, windows, R@k} for one difficulty."""
    room_embeddings = [emb for _, _, emb in rooms]
    patches = [query_patches(difficulty, rooms[i][0], q["patch_embeddings"]) for i, q in queries]
    capacity = max(e.shape[0] for e in room_embeddings)
    pool = Gallery.from_embeddings(room_embeddings, object_capacity=capacity)
    frame_scores = [np.asarray(retrieve(p, pool).frame_scores, np.float64) for p in patches]
    rng = np.random.default_rng(seed)
    rows = []
    for length in LENGTHS:
        window_scores, truth = [], []
        for (index, _), scores in zip(queries, frame_scores, strict=True):
            for start in range(0, scores.shape[0] - length + 1, length):
                window_scores.append(scores[start : start + length].sum(axis=0))
                truth.append(index)
        window_scores = np.array(window_scores)
        for candidates in CANDIDATES:
            ranks = []
            for scores, true in zip(window_scores, truth, strict=True):
                others = np.setdiff1d(np.arange(len(rooms)), [true])
                for _ in range(draws):
                    chosen = np.concatenate([[true], rng.choice(others, candidates - 1, False)])
                    ranks.append(int(true_rank(scores[chosen], 0)))
            recalls = recall_at_k(np.array(ranks), KS)
            rows.append(
                {
                    "difficulty": difficulty.name,
                    "frames": length,
                    "candidates": candidates,
                    "windows": len(truth),
                    "draws": draws,
                    **{f"R@{k}": recalls[k] for k in KS},
                }
            )
    check_window(pool, patches[0], frame_scores[0], capacity, room_embeddings, queries[0][0])
    return rows, pool


def check_window(pool, patches, frame_scores, capacity, room_embeddings, true_index) -> None:
    """A direct ``retrieve`` on one window and a candidate sub-gallery equals the summed frame
    scores the table uses."""
    chosen = [true_index] + [i for i in range(len(room_embeddings)) if i != true_index][:9]
    sub = Gallery.from_embeddings([room_embeddings[i] for i in chosen], object_capacity=capacity)
    direct = np.asarray(retrieve(patches[5:15], sub).scores)
    np.testing.assert_allclose(direct, frame_scores[5:15, chosen].sum(axis=0), rtol=1e-5)


def time_queries(pool: Gallery, patches: np.ndarray, repeats: int) -> dict:
    """Median ms per :func:`retrieve` call after compilation, per (length, candidates)."""
    out = {}
    for candidates in CANDIDATES:
        gallery = jax.tree.map(lambda a, n=candidates: a[:n], pool)
        for length in LENGTHS:
            query = patches[:length]
            retrieve(query, gallery).scores.block_until_ready()  # compile
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                retrieve(query, gallery).scores.block_until_ready()
                times.append(time.perf_counter() - start)
            out[(length, candidates)] = 1e3 * float(np.median(times))
    return out


def write_results(rows, timings, pool: Gallery, args, command: str) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    storage = pool.storage_mb()
    objects = pool.num_objects()
    lines = [
        "# Sequential scene retrieval (SG2Loc Table 5 shape), synthetic indoor scenes",
        "",
        f"Command: `{command}`",
        "",
        f"Pool: {len(storage)} rooms ({args.queries} with a {args.frames}-frame query episode "
        f"from `make_episode`, seeds {1000}-{1000 + args.queries - 1}; the rest from "
        f"`make_room`, seeds from 5000), 160x90 images, 9x16 patches, d = "
        f"{pool.embedding_dim}, {objects.min()}-{objects.max()} objects per room (mean "
        f"{objects.mean():.1f}). Windows: non-overlapping, per query episode. Each window is "
        f"ranked among 10 / 50 candidates (its room + random others), {args.draws} draws per "
        "window. See the script's docstring for the difficulty settings.",
        "",
        f"Storage per scene (float32 object embeddings): mean {storage.mean():.3f} MB, max "
        f"{storage.max():.3f} MB (paper, 3RScan: 5.4 MB).",
        "",
        "Time per query: median of repeated `retrieve` calls after compilation, wall clock on 2 "
        "CPU cores shared with other jobs (load average well above 2), so noisy and inflated.",
        "",
    ]
    for difficulty in DIFFICULTIES:
        sub = [r for r in rows if r["difficulty"] == difficulty.name]
        lines += [
            f"## {difficulty.name}",
            "",
            "| frames | windows | R@1 (10) | R@3 (10) | R@5 (10) | ms (10) "
            "| R@1 (50) | R@3 (50) | R@5 (50) | ms (50) | storage MB |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for length in LENGTHS:
            cells = []
            for candidates in CANDIDATES:
                (row,) = [r for r in sub if r["frames"] == length and r["candidates"] == candidates]
                cells += [f"{row[f'R@{k}']:.2f}" for k in KS]
                cells.append(f"{timings[(length, candidates)]:.1f}")
            lines.append(
                f"| {length} | {row['windows']} | "
                + " | ".join(cells)
                + f" | {storage.mean():.3f} |"
            )
        r1 = {
            c: [
                next(r["R@1"] for r in sub if r["frames"] == n and r["candidates"] == c)
                for n in LENGTHS
            ]
            for c in CANDIDATES
        }
        verdicts = []
        for c in CANDIDATES:
            monotone = all(b >= a for a, b in zip(r1[c][:-1], r1[c][1:], strict=True))
            verdicts.append(
                f"{c} candidates: R@1 {r1[c][0]:.2f} (1 frame) -> {r1[c][-1]:.2f} (50 frames), "
                + ("non-decreasing in length" if monotone else "NOT monotone in length")
            )
        lines += ["", "R@1 vs sequence length: " + "; ".join(verdicts) + ".", ""]
    lines += ["## Exploratory runs (not reproduced by this command)", "", EXPLORATORY]
    write_text_atomic(OUT / "table5.md", "\n".join(lines) + "\n")
    fd, tmp = tempfile.mkstemp(prefix="table5.csv.", suffix=".tmp", dir=OUT)
    with os.fdopen(fd, "w", newline="") as f:
        f.write(f"# {command}\n")
        fields = list(rows[0]) + ["ms_per_query", "storage_mb_mean"]
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for row in rows:
            ms = timings[(row["frames"], row["candidates"])]
            writer.writerow({**row, "ms_per_query": ms, "storage_mb_mean": storage.mean()})
    os.chmod(tmp, 0o644)
    os.replace(tmp, OUT / "table5.csv")


EXPLORATORY = (
    "Ad hoc scripts on the same cache (3-4 query episodes, 100 frames, 10 candidates: the true "
    "room + 9 random pool rooms, 5 draws or one fixed draw) before the table was run, reporting "
    "R@1 at 1 and 10 frames. All gave 1.00 / 1.00: rooms' embeddings redrawn with class "
    "similarity s = 0.8 or 0.9 and patch cosines 0.3-0.6 or 0.2-0.5 (30 % confused); d = 64 with "
    "s = 0.8 or 0.5; a per-object query/map appearance gap (query-side object embedding at cosine "
    "0.63, 0.45 or 0.32 to the map's) at s = 0.5, 0.9 or 0.95. Replacing 80 % / 90 % of the "
    "patches by random-class objects gave R@1 0.08 / 0.00 (1 frame) and 0.00 / 0.00 (10 frames): "
    "below chance (0.1), probably because the score is not normalised per scene (rooms with "
    "more objects and classes can explain unrelated patches better, and summing frames "
    "compounds such a bias; not verified here)."
)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--cache", type=Path, default=Path("/tmp/jaxloc_retrieval_cache"))
    parser.add_argument("--queries", type=int, default=8, help="rooms with a query episode")
    parser.add_argument("--distractors", type=int, default=46, help="rooms without a query")
    parser.add_argument("--frames", type=int, default=100, help="frames per query episode")
    parser.add_argument("--draws", type=int, default=10, help="candidate draws per window")
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per shape")
    parser.add_argument("--generate-only", action="store_true")
    args = parser.parse_args()
    command = "JAX_PLATFORMS=cpu python experiments/retrieval_table5.py " + " ".join(sys.argv[1:])
    query_seeds = range(1000, 1000 + args.queries)
    distractor_seeds = range(5000, 5000 + args.distractors)
    generate(args.cache, query_seeds, distractor_seeds, args.frames)
    if args.generate_only:
        return
    rooms, queries = load_pool(args.cache, query_seeds, distractor_seeds)
    if len(rooms) < max(CANDIDATES):
        raise SystemExit(f"the pool has {len(rooms)} rooms; 50 candidates need at least 50")
    rows = []
    for difficulty in DIFFICULTIES:
        start = time.perf_counter()
        result, pool = evaluate(difficulty, rooms, queries, args.draws, seed=7)
        rows += result
        print(f"{difficulty.name}: {time.perf_counter() - start:.0f} s", flush=True)
        for row in result:
            print(row, flush=True)
    timings = time_queries(pool, queries[0][1]["patch_embeddings"], args.repeats)
    write_results(rows, timings, pool, args, command)


if __name__ == "__main__":
    main()
