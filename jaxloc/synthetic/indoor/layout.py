"""Furniture placement and scene changes on the floor plan of a rectangular room (host-side numpy).

An object's placement is a rigid 2-D transform of its local frame (see
:mod:`jaxloc.synthetic.indoor.meshes`) plus the height of its base:
``world = R_z(angle) local + (x, y, elevation)``. Its footprint is the rotated rectangle
``|local x| <= half_extent[0], |local y| <= half_extent[1]`` over the height interval
``[elevation, elevation + height]``. Two objects collide when their height intervals overlap and
their footprints overlap (separating-axis test), with a small tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Metres between a wall and the back of an object standing or hung against it.
WALL_GAP = 0.01
#: Metres of overlap of two objects' boxes still accepted (touching objects do not collide).
TOLERANCE = 0.02


@dataclass(frozen=True)
class Placement:
    """Where one object stands: footprint centre (x, y), yaw ``angle`` of its local x axis,
    footprint half extents (metres), base ``elevation`` and ``height`` (metres), its mount
    ("floor", "floor_wall" or "wall")."""

    center: tuple[float, float]
    angle: float
    half_extent: tuple[float, float]
    elevation: float
    height: float
    mount: str

    def corners(self, margin: float = 0.0) -> np.ndarray:
        """(4, 2) footprint corners in the world, grown by ``margin`` metres."""
        hx, hy = self.half_extent[0] + margin, self.half_extent[1] + margin
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        return local @ _rotation(self.angle).T + np.asarray(self.center)

    def transform(self) -> np.ndarray:
        """4x4 world-from-local transform."""
        matrix = np.eye(4)
        matrix[:2, :2] = _rotation(self.angle)
        matrix[:3, 3] = (*self.center, self.elevation)
        return matrix


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def wall_frame(size, wall: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Start corner (2,), unit direction (2,) and length of wall ``wall`` of a room of ``size``;
    the room interior lies to the left of the direction."""
    lx, ly = size[0], size[1]
    corners = np.array([[0.0, 0.0], [lx, 0.0], [lx, ly], [0.0, ly]])
    start, end = corners[wall], corners[(wall + 1) % 4]
    length = float(np.linalg.norm(end - start))
    return start, (end - start) / length, length


def against_wall(size, wall: int, along: float, half_extent, elevation, height, mount) -> Placement:
    """An object with its back (local -y) against ``wall``, centred ``along`` metres along it."""
    start, direction, _ = wall_frame(size, wall)
    inward = np.array([-direction[1], direction[0]])
    center = start + along * direction + (half_extent[1] + WALL_GAP) * inward
    angle = float(np.arctan2(direction[1], direction[0]))  # local x along the wall, +y inward
    return Placement(tuple(center), angle, tuple(half_extent), elevation, height, mount)


def _footprints_overlap(a: Placement, b: Placement) -> bool:
    ca, cb = a.corners(-TOLERANCE / 2), b.corners(-TOLERANCE / 2)
    for angle in (a.angle, b.angle):
        for axis in (
            np.array([np.cos(angle), np.sin(angle)]),
            np.array([-np.sin(angle), np.cos(angle)]),
        ):
            pa, pb = ca @ axis, cb @ axis
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


def collides(a: Placement, b: Placement) -> bool:
    """True when the two objects' boxes overlap by more than the tolerance."""
    low, high = max(a.elevation, b.elevation), min(a.elevation + a.height, b.elevation + b.height)
    return high - low > TOLERANCE and _footprints_overlap(a, b)


def inside_room(p: Placement, size) -> bool:
    corners = p.corners()
    return bool(
        np.all(corners >= -1e-6)
        and np.all(corners <= np.asarray(size[:2]) + 1e-6)
        and p.elevation + p.height <= size[2] - 0.05
    )


def fits(p: Placement, others: list[Placement], size) -> bool:
    """Inside the room and colliding with none of ``others``."""
    return inside_room(p, size) and not any(collides(p, o) for o in others)


def door_clearance(door: Placement) -> Placement:
    """The swing area in front of a door (its local +y side), kept free of floor objects."""
    width = 2 * door.half_extent[0]
    inward = np.array([-np.sin(door.angle), np.cos(door.angle)])
    center = np.asarray(door.center) + (door.half_extent[1] + width / 2) * inward
    return Placement(tuple(center), door.angle, (width / 2, width / 2), 0.0, 2.0, "floor")


def walkway(size, rng: np.random.Generator, fraction: float) -> Placement:
    """A free rectangle near the room centre (``fraction`` of each side) kept for the camera."""
    lx, ly = size[0], size[1]
    center = (lx / 2 + rng.uniform(-0.1, 0.1) * lx, ly / 2 + rng.uniform(-0.1, 0.1) * ly)
    return Placement(center, 0.0, (fraction * lx / 2, fraction * ly / 2), 0.0, size[2], "floor")


def sample_placement(rng: np.random.Generator, size, mount: str, dims, elevation) -> Placement:
    """A random placement of an object with (width, depth, height) ``dims`` and the given mount."""
    half = (dims[0] / 2, dims[1] / 2)
    if mount == "floor":
        angle = rng.uniform(-np.pi, np.pi)
        reach = np.hypot(*half)
        center = rng.uniform(reach, np.maximum(np.asarray(size[:2]) - reach, reach + 1e-3))
        return Placement(tuple(center), float(angle), half, 0.0, dims[2], mount)
    wall = int(rng.integers(4))
    _, _, length = wall_frame(size, wall)
    along = rng.uniform(half[0], max(length - half[0], half[0] + 1e-3))
    return against_wall(size, wall, along, half, elevation, dims[2], mount)


def moved(rng: np.random.Generator, p: Placement, size) -> Placement:
    """A random displacement of ``p``: wall-hung objects slide along their wall, floor objects
    shift 0.3-1.0 m and turn up to 45 degrees."""
    distance = rng.uniform(0.3, 1.0)
    if p.mount == "wall":
        direction = np.array([np.cos(p.angle), np.sin(p.angle)]) * rng.choice([-1.0, 1.0])
        return Placement(
            tuple(np.asarray(p.center) + distance * direction),
            p.angle,
            p.half_extent,
            p.elevation,
            p.height,
            p.mount,
        )
    heading = rng.uniform(-np.pi, np.pi)
    center = np.asarray(p.center) + distance * np.array([np.cos(heading), np.sin(heading)])
    angle = p.angle + rng.uniform(-np.pi / 4, np.pi / 4)
    return Placement(tuple(center), float(angle), p.half_extent, p.elevation, p.height, p.mount)
