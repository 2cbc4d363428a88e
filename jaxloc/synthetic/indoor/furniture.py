"""The furniture vocabulary of the synthetic indoor world: 19 classes, each a few primitives.

Every object is built in its local frame: x across the object's width, y from its back (-y) to
its front (+y), z up from its base at z = 0, footprint centred on the origin. Sizes are
(width, depth, height) in metres; colours RGB in [0, 1].
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

#: Class names of the structure objects, the first entries of :data:`CLASS_NAMES`.
STRUCTURE_CLASSES = ("floor", "ceiling", "wall")


@dataclass(frozen=True)
class Part:
    """One primitive of an object: triangles, base colour (RGB in [0, 1]) and texture kind."""

    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float]
    pattern: str


@dataclass(frozen=True)
class ClassSpec:
    """How one furniture class is sized, placed and built.

    Attributes:
        name: class name.
        mount: "floor" (anywhere on the floor), "floor_wall" (on the floor, back to a wall) or
            "wall" (hung on a wall at ``elevation``).
        size_min, size_max: (width, depth, height) ranges in metres.
        elevation: (min, max) height of the object's base above the floor, metres.
        movable: whether scene changes may move or remove it (doors and windows stay).
        weight: relative sampling frequency.
        max_count: at most this many per room.
    """

    name: str
    mount: str
    size_min: tuple[float, float, float]
    size_max: tuple[float, float, float]
    elevation: tuple[float, float] = (0.0, 0.0)
    movable: bool = True
    weight: float = 1.0
    max_count: int = 8


def _box(center, extents) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.box(extents=extents)
    return mesh.vertices + np.asarray(center, float), mesh.faces


def _cylinder(center, radius, height, sections=10) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    return mesh.vertices + np.asarray(center, float), mesh.faces


def _part(geometry, color, pattern="noise") -> Part:
    return Part(geometry[0], geometry[1], tuple(color), pattern)


def _jitter(rng: np.random.Generator, color, spread=0.08) -> np.ndarray:
    return np.clip(np.asarray(color) + rng.uniform(-spread, spread, 3), 0.05, 0.95)


#: Wood base colours (RGB in [0, 1]); :func:`pick` draws one of a palette and jitters it +-0.08.
WOOD = ((0.55, 0.38, 0.22), (0.72, 0.55, 0.35), (0.40, 0.26, 0.15), (0.85, 0.75, 0.60))
#: Fabric base colours (RGB in [0, 1]).
FABRIC = ((0.30, 0.35, 0.55), (0.60, 0.25, 0.25), (0.45, 0.55, 0.40), (0.70, 0.65, 0.55))
#: Painted-surface base colours (RGB in [0, 1]).
PAINT = ((0.90, 0.90, 0.88), (0.25, 0.25, 0.28), (0.75, 0.80, 0.85), (0.55, 0.60, 0.50))
#: Metal base colours (RGB in [0, 1]).
METAL = ((0.60, 0.60, 0.62), (0.20, 0.20, 0.22), (0.80, 0.78, 0.72))


def pick(rng: np.random.Generator, palette) -> np.ndarray:
    return _jitter(rng, palette[rng.integers(len(palette))])


def _legs(w, d, h, thickness, color, inset=0.04) -> list[Part]:
    xs, ys = w / 2 - inset - thickness / 2, d / 2 - inset - thickness / 2
    return [
        _part(_box((sx * xs, sy * ys, h / 2), (thickness, thickness, h)), color, "plain")
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]


def _bed(rng, w, d, h):
    wood, cloth = pick(rng, WOOD), pick(rng, FABRIC)
    return [
        _part(_box((0, 0, 0.15), (w, d, 0.3)), wood, "stripes"),
        _part(_box((0, 0.03, 0.41), (w - 0.06, d - 0.1, 0.22)), cloth, "stripes"),
        _part(_box((0, -d / 2 + 0.04, h / 2), (w, 0.08, h)), wood, "stripes"),
        _part(_box((-w / 4, -d / 2 + 0.3, 0.58), (w * 0.4, 0.35, 0.12)), pick(rng, PAINT)),
        _part(_box((w / 4, -d / 2 + 0.3, 0.58), (w * 0.4, 0.35, 0.12)), pick(rng, PAINT)),
    ]


def _chair(rng, w, d, h):
    wood, cloth = pick(rng, WOOD), pick(rng, FABRIC)
    seat = 0.45
    return [
        _part(_box((0, 0, seat), (w, d, 0.05)), cloth, "checker"),
        _part(_box((0, -d / 2 + 0.02, (seat + h) / 2), (w, 0.04, h - seat)), wood, "stripes"),
        *_legs(w, d, seat - 0.025, 0.04, wood, inset=0.0),
    ]


def _table(rng, w, d, h):
    wood = pick(rng, WOOD)
    return [
        _part(_box((0, 0, h - 0.02), (w, d, 0.04)), wood, "stripes"),
        *_legs(w, d, h - 0.04, 0.06, _jitter(rng, wood)),
    ]


def _sofa(rng, w, d, h, arm=0.18):
    cloth = pick(rng, FABRIC)
    return [
        _part(_box((0, 0.05, 0.21), (w - 2 * arm, d - 0.1, 0.42)), cloth, "checker"),
        _part(_box((0, -d / 2 + 0.1, h / 2), (w, 0.2, h)), _jitter(rng, cloth), "stripes"),
        _part(_box((-w / 2 + arm / 2, 0, 0.3), (arm, d, 0.6)), cloth, "noise"),
        _part(_box((w / 2 - arm / 2, 0, 0.3), (arm, d, 0.6)), cloth, "noise"),
    ]


def _armchair(rng, w, d, h):
    return _sofa(rng, w, d, h, arm=0.15)


def _cabinet(rng, w, d, h):
    body, metal = pick(rng, WOOD + PAINT), pick(rng, METAL)
    door_w = w / 2 - 0.03
    return [
        _part(_box((0, 0, h / 2), (w, d, h)), body, "stripes"),
        _part(_box((-w / 4, d / 2 + 0.01, h / 2), (door_w, 0.02, h - 0.1)), _jitter(rng, body)),
        _part(_box((w / 4, d / 2 + 0.01, h / 2), (door_w, 0.02, h - 0.1)), _jitter(rng, body)),
        _part(_box((-0.04, d / 2 + 0.03, h * 0.55), (0.02, 0.02, 0.15)), metal, "plain"),
        _part(_box((0.04, d / 2 + 0.03, h * 0.55), (0.02, 0.02, 0.15)), metal, "plain"),
    ]


def _nightstand(rng, w, d, h):
    body = pick(rng, WOOD)
    return [
        _part(_box((0, 0, h / 2), (w, d, h)), body, "stripes"),
        _part(_box((0, d / 2 + 0.01, h * 0.72), (w - 0.06, 0.02, h * 0.4)), pick(rng, PAINT)),
        _part(_box((0, d / 2 + 0.01, h * 0.27), (w - 0.06, 0.02, h * 0.4)), pick(rng, PAINT)),
    ]


def _shelf(rng, w, d, h):
    wood = pick(rng, WOOD)
    parts = [
        _part(_box((-w / 2 + 0.015, 0, h / 2), (0.03, d, h)), wood, "stripes"),
        _part(_box((w / 2 - 0.015, 0, h / 2), (0.03, d, h)), wood, "stripes"),
        _part(_box((0, -d / 2 + 0.005, h / 2), (w, 0.01, h)), _jitter(rng, wood), "noise"),
    ]
    levels = np.linspace(0.02, h - 0.02, 5)
    for z in levels:
        parts.append(_part(_box((0, 0, z), (w - 0.06, d, 0.025)), wood, "stripes"))
    for z0 in levels[:-1]:  # a row of books on each board
        x = -w / 2 + 0.05
        while x < w / 2 - 0.15:
            bw, bh = rng.uniform(0.03, 0.08), rng.uniform(0.15, 0.25)
            parts.append(
                _part(
                    _box((x + bw / 2, 0, z0 + 0.013 + bh / 2), (bw, d * 0.8, bh)),
                    rng.uniform(0.1, 0.9, 3),
                    "plain",
                )
            )
            x += bw + rng.uniform(0.0, 0.1)
            if len(parts) > 24:
                break
    return parts


def _desk(rng, w, d, h):
    wood = pick(rng, WOOD + PAINT)
    return [
        _part(_box((0, 0, h - 0.02), (w, d, 0.04)), wood, "stripes"),
        _part(_box((-w / 2 + 0.02, 0, (h - 0.04) / 2), (0.04, d, h - 0.04)), wood, "noise"),
        _part(_box((w / 2 - 0.2, 0, (h - 0.04) / 2), (0.4, d, h - 0.04)), _jitter(rng, wood)),
        _part(_box((w / 2 - 0.2, d / 2 + 0.01, h * 0.6), (0.34, 0.02, 0.12)), pick(rng, PAINT)),
    ]


def _lamp(rng, w, d, h):
    metal, shade = pick(rng, METAL), pick(rng, PAINT + FABRIC)
    return [
        _part(_cylinder((0, 0, 0.015), w * 0.4, 0.03), metal, "plain"),
        _part(_cylinder((0, 0, (h - 0.3) / 2), 0.015, h - 0.3, sections=6), metal, "plain"),
        _part(_cylinder((0, 0, h - 0.15), w / 2, 0.3, sections=14), shade, "stripes"),
    ]


def _plant(rng, w, d, h):
    pot_h = 0.3 * h
    foliage = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    radius = min(w / 2, (h - pot_h) / 2)
    scale = radius * rng.uniform(0.8, 1.15, size=(len(foliage.vertices), 1))
    verts = foliage.vertices * scale + np.array([0.0, 0.0, h - radius])
    return [
        _part(
            _cylinder((0, 0, pot_h / 2), w * 0.3, pot_h, sections=12), pick(rng, PAINT), "stripes"
        ),
        Part(verts, foliage.faces, tuple(_jitter(rng, (0.2, 0.5, 0.2))), "noise"),
    ]


def _tv(rng, w, d, h):
    return [
        _part(_box((0, 0, h / 2), (w, d, h)), _jitter(rng, (0.1, 0.1, 0.1), 0.04), "plain"),
        _part(
            _box((0, d / 2 + 0.005, h / 2), (w - 0.05, 0.01, h - 0.05)),
            rng.uniform(0.1, 0.7, 3),
            "noise",
        ),
    ]


def _box_object(rng, w, d, h):
    card = _jitter(rng, (0.65, 0.5, 0.32))
    return [
        _part(_box((0, 0, h / 2), (w, d, h)), card, "noise"),
        _part(_box((0, 0, h + 0.002), (0.06, d + 0.004, 0.004)), _jitter(rng, (0.8, 0.75, 0.6))),
    ]


def _door(rng, w, d, h):
    slab, frame = pick(rng, WOOD + PAINT), pick(rng, PAINT)
    return [
        _part(_box((0, 0, h / 2), (w - 0.1, d, h - 0.05)), slab, "stripes"),
        _part(_box((-w / 2 + 0.025, 0.005, h / 2), (0.05, d + 0.01, h)), frame, "plain"),
        _part(_box((w / 2 - 0.025, 0.005, h / 2), (0.05, d + 0.01, h)), frame, "plain"),
        _part(_box((0, 0.005, h - 0.025), (w, d + 0.01, 0.05)), frame, "plain"),
        _part(_cylinder((w / 2 - 0.15, d / 2 + 0.03, 1.0), 0.02, 0.06), pick(rng, METAL), "plain"),
    ]


def _window(rng, w, d, h):
    frame = pick(rng, PAINT + WOOD)
    glass = _jitter(rng, (0.55, 0.7, 0.85), 0.05)
    return [
        _part(_box((0, 0, h / 2), (w - 0.1, 0.01, h - 0.1)), glass, "noise"),
        _part(_box((-w / 2 + 0.025, 0, h / 2), (0.05, d, h)), frame, "plain"),
        _part(_box((w / 2 - 0.025, 0, h / 2), (0.05, d, h)), frame, "plain"),
        _part(_box((0, 0, 0.025), (w, d, 0.05)), frame, "plain"),
        _part(_box((0, 0, h - 0.025), (w, d, 0.05)), frame, "plain"),
        _part(_box((0, 0, h / 2), (0.04, d, h)), frame, "plain"),
    ]


def _picture(rng, w, d, h):
    return [
        _part(_box((0, 0, h / 2), (w, d, h)), pick(rng, WOOD + METAL), "plain"),
        _part(
            _box((0, d / 2 + 0.003, h / 2), (w - 0.06, 0.006, h - 0.06)),
            rng.uniform(0.15, 0.9, 3),
            "checker",
        ),
    ]


def _trash_can(rng, w, d, h):
    color = pick(rng, METAL + PAINT)
    return [
        _part(_cylinder((0, 0, h / 2), w / 2, h, sections=16), color, "stripes"),
        _part(_cylinder((0, 0, h + 0.01), w / 2 + 0.01, 0.02, sections=16), _jitter(rng, color)),
    ]


def _radiator(rng, w, d, h):
    color = _jitter(rng, (0.88, 0.88, 0.86), 0.04)
    count = max(3, int(w / 0.08))
    xs = np.linspace(-w / 2 + 0.02, w / 2 - 0.02, count)
    parts = [_part(_box((x, 0, h / 2), (0.04, d, h)), color, "plain") for x in xs]
    parts.append(_part(_box((0, -d / 4, h / 2), (w, d / 2, h * 0.8)), _jitter(rng, color)))
    return parts


def _stool(rng, w, d, h):
    wood = pick(rng, WOOD + METAL)
    return [
        _part(_cylinder((0, 0, h - 0.02), w / 2, 0.04, sections=16), pick(rng, FABRIC), "checker"),
        *_legs(w * 0.8, d * 0.8, h - 0.04, 0.03, wood),
    ]


#: The furniture classes, in class order: each one's :class:`ClassSpec` and its parts' builder.
FURNITURE: tuple[tuple[ClassSpec, Callable], ...] = (
    (
        ClassSpec("bed", "floor_wall", (1.4, 1.9, 0.9), (1.8, 2.1, 1.1), weight=0.5, max_count=2),
        _bed,
    ),
    (ClassSpec("chair", "floor", (0.42, 0.42, 0.85), (0.5, 0.5, 1.0), weight=2.0), _chair),
    (ClassSpec("table", "floor", (0.8, 0.7, 0.72), (1.6, 0.95, 0.78), max_count=3), _table),
    (
        ClassSpec(
            "sofa", "floor_wall", (1.6, 0.8, 0.75), (2.2, 0.95, 0.9), weight=0.6, max_count=2
        ),
        _sofa,
    ),
    (ClassSpec("cabinet", "floor_wall", (0.6, 0.4, 0.8), (1.2, 0.6, 1.9)), _cabinet),
    (ClassSpec("shelf", "floor_wall", (0.6, 0.28, 1.2), (1.0, 0.4, 2.0)), _shelf),
    (ClassSpec("desk", "floor_wall", (1.0, 0.6, 0.73), (1.6, 0.75, 0.77), weight=0.7), _desk),
    (ClassSpec("lamp", "floor", (0.35, 0.35, 1.4), (0.45, 0.45, 1.7), weight=0.8), _lamp),
    (ClassSpec("plant", "floor", (0.3, 0.3, 0.6), (0.6, 0.6, 1.4)), _plant),
    (
        ClassSpec(
            "tv", "wall", (0.9, 0.06, 0.55), (1.4, 0.08, 0.8), (0.9, 1.2), weight=0.5, max_count=2
        ),
        _tv,
    ),
    (ClassSpec("box", "floor", (0.3, 0.3, 0.25), (0.6, 0.5, 0.5), weight=1.5), _box_object),
    (
        ClassSpec(
            "door",
            "wall",
            (0.8, 0.05, 2.0),
            (0.9, 0.06, 2.1),
            movable=False,
            weight=0.7,
            max_count=2,
        ),
        _door,
    ),
    (
        ClassSpec(
            "window",
            "wall",
            (0.8, 0.08, 1.0),
            (1.6, 0.1, 1.4),
            (0.8, 1.0),
            movable=False,
            max_count=4,
        ),
        _window,
    ),
    (
        ClassSpec("picture", "wall", (0.4, 0.03, 0.3), (1.0, 0.04, 0.8), (1.2, 1.5), weight=1.5),
        _picture,
    ),
    (
        ClassSpec("trash_can", "floor", (0.25, 0.25, 0.35), (0.35, 0.35, 0.6), weight=0.8),
        _trash_can,
    ),
    (
        ClassSpec("nightstand", "floor_wall", (0.4, 0.35, 0.45), (0.55, 0.45, 0.6), weight=0.6),
        _nightstand,
    ),
    (ClassSpec("armchair", "floor", (0.75, 0.75, 0.8), (0.9, 0.9, 0.95), weight=0.6), _armchair),
    (
        ClassSpec(
            "radiator",
            "wall",
            (0.6, 0.1, 0.5),
            (1.2, 0.12, 0.7),
            (0.1, 0.2),
            movable=False,
            weight=0.6,
            max_count=3,
        ),
        _radiator,
    ),
    (ClassSpec("stool", "floor", (0.3, 0.3, 0.45), (0.4, 0.4, 0.75), weight=0.8), _stool),
)

#: Every class name, indexed by class id: :data:`STRUCTURE_CLASSES`, then the furniture classes.
CLASS_NAMES: tuple[str, ...] = STRUCTURE_CLASSES + tuple(spec.name for spec, _ in FURNITURE)
