"""SG2Loc's per-frame verdict across conditions: the library's rule, and a calibrated logistic
confidence as a candidate, on development conditions and on a held-out generator variant.

Every seed draws one **condition** (:func:`draw_condition`): image size (160x90 to 960x540),
strides, particle capacity, likelihood width ``sigma`` (0.2-1.0) and weights, with or without
depth and colour, camera heights between the configured ones (1.5-1.8 m; 60 % of the conditions)
and beyond them (1.0-1.6 m or 1.85-2.35 m), depth noise and holes (up to most of the depth
missing), patch confusion, colour noise and mesh coarseness. For each seed two sequences of
``--frames`` frames:

* ``right``: ``make_episode(seed)``, the camera in the map's own (changed) room;
* ``wrong``: ``make_lookalike_episode(seed, seed + PLACE_OFFSET)``, a look-alike wrong place (the
  camera in another room whose objects carry the map's embeddings of their class).

Each is localized offline (:func:`jaxloc.sg2loc.localize`) and as a stream
(:func:`jaxloc.sg2loc.online.filter_sequence`, no relocalization, so that every frame's evidence
is the filter's own), and every frame's evidence (:class:`~jaxloc.sg2loc.Verdict`), errors and
condition are appended to ``frames_<split>.csv`` (a rerun skips the runs already there).

The development split uses the ``"relative"`` depth model of
:class:`~jaxloc.synthetic.indoor.SensorConfig`; the held-out split (``--variant kinect``) the
``"kinect"`` model (distance-squared noise, no depth beyond 4.5 m or across edges), a generator
variant nothing was chosen on, at the sizes given by ``--sizes``.

``--fit SPLIT`` prints the candidate's weights (the library's
:data:`~jaxloc.sg2loc._verdict.CONFIDENCE_WITH_DEPTH` and ``_WITHOUT_DEPTH`` are the fit on the
development split) and threshold. ``--report SPLIT`` judges, per condition group and mode, the
library's rule
(:data:`~jaxloc.sg2loc._verdict.VERDICT_WITH_DEPTH` / ``_WITHOUT_DEPTH`` applied to the logged
evidence) and the candidate: a logistic model of being within 0.5 m and 10 degrees over the
evidence (logit of the posterior mass, semantic fraction, depth deficit; weights >= 0) and what the
step knows (log sigma, log rays per particle, log capacity), fitted on the development split, its
threshold the smallest that keeps >= 97 % of the flagged frames right and <= 2 % of the
wrong-place frames flagged on out-of-fold confidences (5 groups of seeds, each predicted by a fit
without it); on the development split itself the candidate's confidences are out of fold. It
ends with the candidate's reliability table. ``--ceiling SPLIT``: the most any logistic rule over
the step's own evidence could flag on a split, fitted and thresholded on that split (an upper
bound, :func:`ceiling`).

    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_conditions.py --split dev \
        --seeds 5100-5159
    JAX_PLATFORMS=cpu python experiments/sg2loc_verdict_conditions.py --split kinect \
        --variant kinect --sizes 320x180,480x270,640x360,960x540 --seeds 7100-7123
    python experiments/sg2loc_verdict_conditions.py --fit dev
    python experiments/sg2loc_verdict_conditions.py --report dev
    python experiments/sg2loc_verdict_conditions.py --report kinect
    python experiments/sg2loc_verdict_conditions.py --ceiling kinect
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
# the look-alike place of map seed s is the room of seed s + PLACE_OFFSET, as in the rule's choice
from sg2loc_verdict import PLACE_OFFSET, parse_seeds  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "sg2loc_verdict_conditions"
#: Image sizes of the development conditions and how often each is drawn (the larger, the
#: costlier on a CPU).
SIZES = {(160, 90): 0.35, (320, 180): 0.3, (480, 270): 0.15, (640, 360): 0.12, (960, 540): 0.08}
#: Stride sets per image width (one drawn per condition).
STRIDES = {
    160: [(10, 6, 4), (8, 4, 2)],
    320: [(20, 8, 4), (10, 6, 4)],
    480: [(20, 8, 4), (16, 8, 4)],
    640: [(20, 8, 4), (16, 8, 4)],
    960: [(20, 8, 4), (30, 12, 6)],
}
CONDITION = [
    "variant", "width", "height", "strides", "capacity", "sigma", "lambda_depth", "lambda_color",
    "use_depth", "use_color", "height_low", "height_high", "depth_noise", "hole_rate",
    "confusion_rate", "rgb_noise", "vertices",
]  # fmt: skip
EVIDENCE = [
    "mass", "spread_x", "spread_y", "spread_z", "spread_yaw", "ess",
    "semantic_fraction", "depth_deficit", "color",
]  # fmt: skip
FIELDS = ["seed", "kind", "mode", "frame", "pos", "rot", *EVIDENCE, "localized", "seconds"]
FIELDS += CONDITION
#: The posterior mass is clipped to [MASS_CLIP, 1 - MASS_CLIP] before its logit.
MASS_CLIP = 0.01
#: Development targets of the threshold on out-of-fold confidences (margins beyond the 95 % /
#: 5 % requirement).
MIN_PRECISION, MAX_FALSE_ACCEPT = 0.97, 0.02


def draw_condition(seed: int, variant: str, sizes: list[tuple[int, int]] | None) -> dict:
    """The condition of a seed (deterministic): what the generator and the filter use."""
    rng = np.random.default_rng([seed, 60])
    if sizes:
        width, height = sizes[seed % len(sizes)]
    else:
        keys = list(SIZES)
        width, height = keys[rng.choice(len(keys), p=list(SIZES.values()))]
    options = STRIDES[width]
    strides = options[rng.integers(len(options))]
    capacity = int(rng.choice([1000, 2500]))
    if rng.random() < 0.6:  # the camera between the configured heights (1.5-1.8 m) ...
        low = float(rng.uniform(1.45, 1.7))
        high = min(low + float(rng.uniform(0.05, 0.2)), 1.85)
    else:  # ... or beyond them, below or above
        low = float(rng.choice([rng.uniform(1.0, 1.3), rng.uniform(1.85, 2.05)]))
        high = low + float(rng.uniform(0.1, 0.3))
    vertices = [(150, 300), (400, 1000)][rng.integers(2)]
    hole_rate = float(rng.choice([rng.uniform(0.0, 0.3), rng.uniform(0.5, 0.8)], p=[0.8, 0.2]))
    return {
        "variant": variant,
        "width": width,
        "height": height,
        "strides": "/".join(map(str, strides)),
        "capacity": capacity,
        "sigma": round(float(rng.uniform(0.2, 1.0)), 3),
        "lambda_depth": round(float(rng.uniform(1.0, 3.0)), 3),
        "lambda_color": round(float(rng.uniform(0.5, 3.0)), 3),
        "use_depth": int(rng.random() < 0.75),
        "use_color": int(rng.random() < 0.75),
        "height_low": round(low, 3),
        "height_high": round(high, 3),
        "depth_noise": round(float(rng.uniform(0.0, 0.05)), 4),
        "hole_rate": round(hole_rate, 3),
        "confusion_rate": round(float(rng.uniform(0.05, 0.4)), 3),
        "rgb_noise": round(float(rng.uniform(0.0, 0.06)), 4),
        "vertices": "-".join(map(str, vertices)),
    }


def episode_config(c: dict):
    from jaxloc.synthetic.indoor import EpisodeConfig, RoomConfig, SensorConfig, TrajectoryConfig

    sensor = SensorConfig(
        width=c["width"],
        height=c["height"],
        depth_noise=c["depth_noise"],
        depth_model=c["variant"],
        hole_rate=c["hole_rate"],
        confusion_rate=c["confusion_rate"],
        rgb_noise=c["rgb_noise"],
    )
    vertices = tuple(int(v) for v in c["vertices"].split("-"))
    return EpisodeConfig(
        room=RoomConfig(vertex_range=vertices),
        trajectory=TrajectoryConfig(height_range=(c["height_low"], c["height_high"])),
        sensor=sensor,
    )


def sg2loc_config(c: dict):
    """The condition's :class:`~jaxloc.sg2loc.SG2LocConfig` (KLD-sampling's floor
    ``c["min_particles"]`` where given, else the default)."""
    from jaxloc.sg2loc import KLDConfig, ObservationConfig, SG2LocConfig

    observation = ObservationConfig(
        use_depth=bool(c["use_depth"]),
        use_color=bool(c["use_color"]),
        sigma=c["sigma"],
        lambda_depth=c["lambda_depth"],
        lambda_color=c["lambda_color"],
    )
    strides = tuple(int(s) for s in str(c["strides"]).split("/"))
    kld = KLDConfig(min_particles=c.get("min_particles", KLDConfig().min_particles))
    return SG2LocConfig(
        capacity=c["capacity"],
        strides=strides,
        observation=observation,
        relocalize_after=0,
        kld=kld,
    )


def rows_of(seed, kind, mode, episode, poses, verdicts, seconds, condition):
    from jaxloc.metrics import yaw_pose_errors

    if episode.in_map:
        pos, rot = yaw_pose_errors(np.asarray(poses), episode.poses_gt)
    else:
        pos = rot = np.full(len(poses), np.nan)
    spread = np.asarray(verdicts.spread)
    for t in range(len(poses)):
        values = {
            "mass": verdicts.mass[t],
            **{f"spread_{a}": spread[t, i] for i, a in enumerate(("x", "y", "z", "yaw"))},
            "ess": verdicts.ess_fraction[t],
            "semantic_fraction": verdicts.semantic_fraction[t],
            "depth_deficit": verdicts.depth_deficit[t],
            "color": verdicts.color[t],
        }
        yield {
            "seed": seed,
            "kind": kind,
            "mode": mode,
            "frame": t,
            "pos": round(float(pos[t]), 4),
            "rot": round(float(rot[t]), 3),
            **{k: round(float(v), 4) for k, v in values.items()},
            "localized": int(verdicts.localized[t]),
            "seconds": round(seconds, 2),
            **condition,
        }


def run_split(split, seeds, frames, variant, sizes) -> None:
    import jax
    from sg2loc_tables import SharedCapacity

    from jaxloc import enable_compilation_cache
    from jaxloc.sg2loc import localize, online
    from jaxloc.synthetic.indoor import make_episode, make_lookalike_episode

    enable_compilation_cache()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"frames_{split}.csv"
    done = set()
    if path.exists():
        with path.open() as f:
            done = {(int(r["seed"]), r["kind"], r["mode"]) for r in csv.DictReader(f)}
    shared = SharedCapacity()
    for seed in seeds:
        if all((seed, k, m) in done for k in ("right", "wrong") for m in ("offline", "online")):
            continue
        # every condition compiles programs of its own shapes: drop them (the disk cache keeps
        # them), or the process runs out of memory mappings after a few dozen conditions
        jax.clear_caches()
        condition = draw_condition(seed, variant, sizes)
        config = sg2loc_config(condition)
        generator = episode_config(condition)
        episodes = [
            ("right", make_episode(seed, frames, generator)),
            ("wrong", make_lookalike_episode(seed, seed + PLACE_OFFSET, frames, generator)),
        ]
        for kind, episode in episodes:
            scene = shared.scene(episode.room)
            seq = episode.sequence
            found = []
            if (seed, kind, "offline") not in done:
                start = time.perf_counter()
                result = localize(jax.random.key(seed), scene, seq, config)
                jax.block_until_ready(result.poses)
                seconds = time.perf_counter() - start
                verdict = jax.tree.map(np.asarray, result.info.verdict)
                found += rows_of(
                    seed, kind, "offline", episode, result.poses, verdict, seconds, condition
                )
            if (seed, kind, "online") not in done:
                start = time.perf_counter()
                stream = online.filter_sequence(jax.random.key(seed), scene, seq, config)
                seconds = time.perf_counter() - start
                found += rows_of(
                    seed, kind, "online", episode, stream.pose, stream.verdict, seconds, condition
                )
            new = not path.exists()
            with path.open("a", newline="") as f:
                writer = csv.DictWriter(f, FIELDS)
                if new:
                    writer.writeheader()
                writer.writerows(found)
            last = [r for r in found if r["frame"] == frames - 1]
            print(
                f"seed {seed} {kind} {condition['width']}x{condition['height']} "
                f"N={condition['capacity']} depth={condition['use_depth']}: last frame "
                + ", ".join(f"{r['mode']} {r['pos']:.2f} m {r['localized']}" for r in last)
                + f" ({sum(r['seconds'] for r in last):.0f} s)",
                flush=True,
            )


def load(split: str) -> dict[str, np.ndarray]:
    with (OUT / f"frames_{split}.csv").open() as f:
        rows = list(csv.DictReader(f))
    text = {"kind", "mode", "variant", "strides", "vertices"}
    return {k: np.array([r[k] for r in rows], None if k in text else float) for k in FIELDS}


def labels(data: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, good, wrong) bool per frame: within 0.5 m and 10 deg in the right room; within
    0.25 m and 5 deg there; a look-alike wrong place's frame."""
    in_room = data["kind"] == "right"
    right = in_room & (data["pos"] < 0.5) & (data["rot"] < 10.0)
    good = in_room & (data["pos"] < 0.25) & (data["rot"] < 5.0)
    return right, good, data["kind"] == "wrong"


#: The names of the candidate's weights, in the order of the columns of :func:`features`; the last
#: four are evidence (weights >= 0).
WEIGHTS = (
    "bias", "sigma_weight", "rays_weight", "particles_weight",
    "mass_weight", "semantic_weight", "depth_weight", "color_weight",
)  # fmt: skip


def rays_per_particle(width: int, height: int, stride: int) -> int:
    """Rays per particle of the library's stride grid (9 x 16 patches)."""
    from jaxloc.camera import Camera, stride_grid

    camera = Camera.from_fov(int(width), int(height), 60.0)
    return int(stride_grid(camera, int(stride), 9, 16).uv.shape[0])


def features(data: dict[str, np.ndarray], use_depth: bool, use_color: bool) -> np.ndarray:
    """(frames, 8) the candidate's terms in the order of :data:`WEIGHTS`: 1, log sigma, log rays
    per particle (the final round's stride offline, the first stride streaming), log capacity,
    logit(mass) (mass clipped to [:data:`MASS_CLIP`, 1 - :data:`MASS_CLIP`]), semantic fraction,
    -depth deficit, colour (zeros for terms not used)."""
    mass = np.clip(data["mass"], MASS_CLIP, 1.0 - MASS_CLIP)
    strides = [s.split("/") for s in data["strides"]]
    stride = [
        int(s[-1] if m == "offline" else s[0]) for s, m in zip(strides, data["mode"], strict=True)
    ]
    cache: dict[tuple, int] = {}
    rays = np.array([
        cache.setdefault(k, rays_per_particle(*k))
        for k in zip(data["width"], data["height"], stride, strict=True)
    ])  # fmt: skip
    ones = np.ones_like(mass)
    depth = -data["depth_deficit"] if use_depth else 0.0 * ones
    color = data["color"] if use_color else 0.0 * ones
    known = [np.log(data["sigma"]), np.log(rays), np.log(data["capacity"])]
    evidence = [np.log(mass / (1 - mass)), data["semantic_fraction"], depth, color]
    return np.stack([ones, *known, *evidence], 1)


def fit_logistic(
    x: np.ndarray, y: np.ndarray, l2: float = 1e-3, nonnegative: int = 4
) -> np.ndarray:
    """Weights of ``P(y) = sigmoid(x @ w)`` by Newton's method, the evidence weights (the last
    ``nonnegative``) kept >= 0: one that would turn negative is fixed at 0 and the rest refitted."""
    free = np.ones(x.shape[1], bool)
    free[np.all(x == 0, axis=0)] = False
    evidence = np.arange(x.shape[1]) >= x.shape[1] - nonnegative
    while True:
        w = np.zeros(x.shape[1])
        for _ in range(100):
            p = 1.0 / (1.0 + np.exp(-(x @ w)))
            grad = x.T @ (p - y) + l2 * w
            hess = (x * (p * (1 - p))[:, None]).T @ x + l2 * np.eye(x.shape[1])
            step = np.zeros_like(w)
            step[free] = np.linalg.solve(hess[np.ix_(free, free)], grad[free])
            w -= step
            if np.max(np.abs(step)) < 1e-8:
                break
        negative = free & evidence & (w < 0)
        if not negative.any():
            return w
        free &= ~negative


def judge(flagged, right, good, wrong, where) -> dict:
    flagged = flagged & where
    return {
        "flagged": int(flagged.sum()),
        "precision": float((flagged & right).sum() / max(flagged.sum(), 1)),
        "recall": float((flagged & good).sum() / max((good & where).sum(), 1)),
        "false_accept": float((flagged & wrong).sum() / max((wrong & where).sum(), 1)),
        "good": int((good & where).sum()),
        "wrong_frames": int((wrong & where).sum()),
    }


def out_of_fold(x, y, seeds, runs, folds: int = 5) -> np.ndarray:
    """Each frame's confidence from a model fitted without its seed's runs (``folds`` groups of
    seeds): what the fit predicts for conditions it has not seen."""
    groups = np.array_split(np.random.default_rng(0).permutation(np.unique(seeds[runs])), folds)
    confidence = np.zeros(len(y))
    for group in groups:
        held = np.isin(seeds, group)
        w = fit_logistic(x[runs & ~held], y[runs & ~held])
        confidence[held] = (1.0 / (1.0 + np.exp(-(x @ w))))[held]
    return confidence


def candidate(dev: dict[str, np.ndarray], use_depth: bool) -> tuple[np.ndarray, float]:
    """The candidate's weights (fitted on every development run of its kind) and threshold
    (chosen on out-of-fold confidences; 1.0 when none meets the targets)."""
    right, good, wrong = labels(dev)
    runs = dev["use_depth"] == use_depth
    x = features(dev, use_depth, False)
    w = fit_logistic(x[runs], right[runs].astype(float))
    confidence = out_of_fold(x, right.astype(float), dev["seed"], runs)
    for threshold in np.linspace(0.3, 0.995, 140):
        flagged = confidence >= threshold
        ok = all(
            s["precision"] >= MIN_PRECISION and s["false_accept"] <= MAX_FALSE_ACCEPT
            for s in (
                judge(flagged, right, good, wrong, runs & (dev["mode"] == m))
                for m in ("offline", "online")
            )
        )
        if ok:
            return w, float(threshold)
    return w, 1.0


def library_weights(use_depth: bool) -> np.ndarray:
    """The library's :class:`~jaxloc.sg2loc.ConfidenceModel` preset as a weight vector."""
    from jaxloc.sg2loc._verdict import default_verdict

    model = default_verdict(use_depth).confidence
    return np.array([float(getattr(model, n)) if hasattr(model, n) else 0.0 for n in WEIGHTS])


def candidate_confidence(data, dev, split_is_dev: bool) -> tuple[np.ndarray, np.ndarray, str]:
    """The confidence and the candidate's threshold per frame of ``data``, and a line on the fit:
    out of fold on the development split, else the library's presets (which must be the fit on
    the development split: the line gives the largest difference)."""
    right = labels(data)[0].astype(float)
    confidence, threshold, notes = np.zeros(len(right)), np.ones(len(right)), []
    for use_depth in (True, False):
        runs = data["use_depth"] == use_depth
        w, t = candidate(dev, use_depth)
        x = features(data, use_depth, False)
        if split_is_dev:
            confidence[runs] = out_of_fold(x, right, data["seed"], runs)[runs]
        else:
            library = library_weights(use_depth)
            confidence[runs] = (1.0 / (1.0 + np.exp(-(x @ library))))[runs]
            notes.append(f"library preset - fit: {np.max(np.abs(library - w)):.3f}")
        threshold[runs] = t
        weights = ", ".join(f"{n}={v:.3f}" for n, v in zip(WEIGHTS, w, strict=True) if v)
        notes.append(
            f"{'with' if use_depth else 'without'} depth: fit {weights}; threshold {t:.3f}"
        )
    return confidence, threshold, "; ".join(notes)


def library_rule(data: dict[str, np.ndarray]) -> np.ndarray:
    """What the library's presets flag on every frame of a split, from its logged evidence."""
    from jaxloc.sg2loc._verdict import default_verdict

    flagged = np.zeros(len(data["seed"]), bool)
    for use_depth in (True, False):
        c = {k: float(v) for k, v in vars(default_verdict(use_depth)).items() if k != "confidence"}
        ok = np.hypot(data["spread_x"], data["spread_y"]) <= c["max_spread_xy"]
        ok &= (data["spread_z"] <= c["max_spread_z"]) & (data["spread_yaw"] <= c["max_spread_yaw"])
        ok &= data["ess"] <= c["max_ess_fraction"]
        ok &= data["semantic_fraction"] >= c["min_semantic_fraction"]
        if use_depth:
            ok &= data["depth_deficit"] <= c["max_depth_deficit"]
        ok &= np.where(data["use_color"] == 1, data["color"] >= c["min_color"], True)
        flagged |= ok & (data["use_depth"] == use_depth)
    return flagged


def report(split: str, dev_split: str = "dev") -> str:
    data, dev = load(split), load(dev_split)
    right, good, wrong = labels(data)
    rule = library_rule(data)
    confidence, threshold, fitted = candidate_confidence(data, dev, split == dev_split)
    chosen = confidence >= threshold
    lines = [
        f"split {split}: {len(set(data['seed']))} seeds, {len(data['seed'])} frames; candidate "
        f"fitted on {dev_split} ({fitted})",
    ]
    if split != dev_split:
        agree = np.mean(rule == data["localized"].astype(bool))
        lines.append(f"the rule from the logged evidence agrees with the run's flags: {agree:.4f}")
    lines += [
        "",
        "P: of the flagged frames within 0.5 m, 10 deg; R: of the frames within 0.25 m, 5 deg "
        "flagged (their count); W: of the wrong-place frames flagged (their count).",
        "",
        "| group | mode | library rule: flagged, P, R, W | candidate: flagged, P, R, W |",
        "|---|---|---|---|",
    ]
    groups = {"all": np.ones(len(right), bool)}
    for width in sorted(set(data["width"])):
        groups[f"{int(width)} px wide"] = data["width"] == width
    groups["with depth"] = data["use_depth"] == 1
    groups["without depth"] = data["use_depth"] == 0
    groups["sigma < 0.5"] = data["sigma"] < 0.5
    groups["sigma >= 0.5"] = data["sigma"] >= 0.5
    groups["depth holes >= 0.5"] = data["hole_rate"] >= 0.5
    groups["camera within the heights"] = (data["height_low"] >= 1.45) & (
        data["height_high"] <= 1.85
    )
    groups["camera beyond the heights"] = ~groups["camera within the heights"]
    for name, where in groups.items():
        for mode in ("offline", "online"):
            cells = []
            for flags in (rule, chosen):
                s = judge(flags, right, good, wrong, where & (data["mode"] == mode))
                cells.append(
                    f"{s['flagged']}, {s['precision']:.3f}, {s['recall']:.3f} ({s['good']}), "
                    f"{s['false_accept']:.3f} ({s['wrong_frames']})"
                )
            lines.append(f"| {name} | {mode} | {cells[0]} | {cells[1]} |")
    lines += ["", "Candidate's reliability (every frame, both modes):", ""]
    lines += ["| confidence | frames | within 0.5 m, 10 deg |", "|---|---|---|"]
    edges = np.linspace(0.0, 1.0, 11)
    for low, high in zip(edges[:-1], edges[1:], strict=True):
        where = (confidence >= low) & ((confidence < high) | (high == 1.0))
        rate = f"{right[where].mean():.3f}" if where.any() else "-"
        lines.append(f"| {low:.1f}-{high:.1f} | {int(where.sum())} | {rate} |")
    return "\n".join(lines)


def ceiling(split: str) -> str:
    """The most a rule over the step's own evidence could flag on ``split``, fitted on it.

    Per kind of run (with or without depth) and mode, a logistic model of being within 0.5 m and
    10 deg over every term the step logs or knows (logit of the mass, the semantic fraction, the
    depth deficit, the logs of the xy, z and yaw spreads and of the ESS fraction, log sigma, log
    rays per particle, log capacity; with and without the colour score; any sign) is fitted on
    the split's own frames, and each group's threshold is the lowest that keeps >= 0.95 of its
    flagged frames right and <= 0.05 of its wrong-place frames flagged. Both choices are made on
    the data judged: an upper bound on what any such rule could reach there, not a result.
    """
    data = load(split)
    right, good, wrong = labels(data)
    spread_xy = np.hypot(data["spread_x"], data["spread_y"])
    spreads = [np.log(v + 1e-3) for v in (spread_xy, data["spread_z"], data["spread_yaw"])]
    lines = [
        f"split {split}: the in-sample ceiling of a logistic rule over the step's evidence "
        "(fitted and thresholded on the frames it judges; P >= 0.95, W <= 0.05 per group)",
        "",
        "| colour score | run | mode | group | threshold | flagged, P, R, W |",
        "|---|---|---|---|---|---|",
    ]
    for use_color in (False, True):
        x = np.column_stack([features(data, True, use_color), *spreads, np.log(data["ess"])])
        for use_depth in (True, False):
            for mode in ("offline", "online"):
                runs = (data["use_depth"] == use_depth) & (data["mode"] == mode)
                w = fit_logistic(x[runs], right[runs].astype(float), nonnegative=0)
                score = x @ w
                groups = {"all": runs}
                for width in sorted(set(data["width"][runs])):
                    groups[f"{int(width)} px wide"] = runs & (data["width"] == width)
                for name, where in groups.items():
                    row = "- | none meets P and W"
                    for t in np.unique(score[where]):
                        s = judge(score >= t, right, good, wrong, where)
                        if s["precision"] >= 0.95 and s["false_accept"] <= 0.05:
                            row = (
                                f"{t:.2f} | {s['flagged']}, {s['precision']:.3f}, "
                                f"{s['recall']:.3f} ({s['good']}), {s['false_accept']:.3f} "
                                f"({s['wrong_frames']})"
                            )
                            break
                    run = "with depth" if use_depth else "without depth"
                    used = "used" if use_color else "left out"
                    lines.append(f"| {used} | {run} | {mode} | {name} | {row} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", help="run the seeds into frames_<split>.csv")
    parser.add_argument("--seeds", type=parse_seeds, default=None, help="e.g. 5000-5079")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--variant", default="relative", help="depth model of the generator")
    parser.add_argument("--sizes", default=None, help="e.g. 320x180,960x540 (default: drawn)")
    parser.add_argument("--fit", metavar="SPLIT", help="fit the confidence's presets on a split")
    parser.add_argument("--report", metavar="SPLIT", help="judge the rule and the candidate")
    parser.add_argument("--ceiling", metavar="SPLIT", help="the in-sample ceiling on a split")
    args = parser.parse_args(argv)
    sizes = None
    if args.sizes:
        sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    if args.split:
        run_split(args.split, args.seeds, args.frames, args.variant, sizes)
    if args.fit:
        data = load(args.fit)
        for use_depth in (True, False):
            w, t = candidate(data, use_depth)
            terms = ", ".join(f"{n}={v:.3f}" for n, v in zip(WEIGHTS, w, strict=True) if v)
            print(f"{'with' if use_depth else 'without'} depth: ConfidenceModel({terms}); the "
                  f"candidate's threshold {t:.3f}")  # fmt: skip
    if args.report:
        print(report(args.report))
    if args.ceiling:
        print(ceiling(args.ceiling))


if __name__ == "__main__":
    main()
