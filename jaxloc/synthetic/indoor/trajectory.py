"""Smooth hand-held camera trajectories through the free floor space of a room (host-side numpy).

The free space is a 5 cm occupancy grid: cells at least ``wall_clearance`` from the walls and
``object_clearance`` from every floor-standing object's footprint, without corridors narrower
than 0.2 m, restricted to the largest connected region. A random walk of straight,
collision-free legs (0.6-2.0 m; turns of about 60 degrees, at most 90 except at dead ends) gives
waypoints; Chaikin corner cutting smooths them into a curve (checked against the free space
again); frames are spaced along it by arc length. The camera looks along the direction of
travel (the chord over +-0.5 m of path, smoothed over frames) plus a slow sinusoidal
look-around, at a height with a slight bob.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from jaxloc.synthetic.indoor.layout import Placement

#: Side of a cell of the free-space grid of camera positions (metres).
CELL = 0.05
#: Gaussian sigma (frames) of the heading smoothing: spreads sharp turns of the path over frames.
HEADING_SMOOTHING = 1.5
#: Metres along the path either side of a frame that define its travel direction.
LOOKAHEAD = 0.5


class FreeSpace:
    """Boolean occupancy grid of the camera's reachable positions on the floor plan."""

    def __init__(self, size, obstacles: list[Placement], wall_clearance, object_clearance):
        self.shape = (int(np.ceil(size[0] / CELL)), int(np.ceil(size[1] / CELL)))
        xs = (np.arange(self.shape[0]) + 0.5) * CELL
        ys = (np.arange(self.shape[1]) + 0.5) * CELL
        px, py = np.meshgrid(xs, ys, indexing="ij")
        free = (
            (px >= wall_clearance)
            & (px <= size[0] - wall_clearance)
            & (py >= wall_clearance)
            & (py <= size[1] - wall_clearance)
        )
        for obstacle in obstacles:
            c, s = np.cos(obstacle.angle), np.sin(obstacle.angle)
            dx, dy = px - obstacle.center[0], py - obstacle.center[1]
            local_x, local_y = c * dx + s * dy, -s * dx + c * dy
            free &= ~(
                (np.abs(local_x) <= obstacle.half_extent[0] + object_clearance)
                & (np.abs(local_y) <= obstacle.half_extent[1] + object_clearance)
            )
        disk = np.hypot(*np.mgrid[-2:3, -2:3]) <= 2.0
        free = ndimage.binary_opening(free, structure=disk)  # drop corridors under 0.2 m wide
        labels, count = ndimage.label(free)
        if count == 0:
            raise RuntimeError("the room has no free floor space for a camera trajectory")
        largest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
        self.free = labels == largest
        self._depth = ndimage.distance_transform_edt(self.free) * CELL

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each (x, y) point of ``points`` (N, 2) lies in a free cell."""
        index = np.floor(points / CELL).astype(int)
        ok = np.all((index >= 0) & (index < np.asarray(self.shape)), axis=1)
        index = np.clip(index, 0, np.asarray(self.shape) - 1)
        return ok & self.free[index[:, 0], index[:, 1]]

    def random_point(self, rng: np.random.Generator) -> np.ndarray:
        """A random free point at least 0.2 m inside the free space where there is such room."""
        cells = np.argwhere(self._depth >= 0.2)
        if len(cells) == 0:
            cells = np.argwhere(self.free)
        return (cells[rng.integers(len(cells))] + rng.uniform(0.2, 0.8, 2)) * CELL


def _segment_free(space: FreeSpace, a: np.ndarray, b: np.ndarray) -> bool:
    count = max(2, int(np.ceil(np.linalg.norm(b - a) / (CELL / 2))) + 1)
    return bool(np.all(space.contains(a + np.linspace(0, 1, count)[:, None] * (b - a))))


def _waypoints(rng: np.random.Generator, space: FreeSpace, length: float) -> np.ndarray | None:
    """A random walk of collision-free straight legs, at least ``length`` metres long (None if
    the walk gets stuck)."""
    points = [space.random_point(rng)]
    heading, total = rng.uniform(-np.pi, np.pi), 0.0
    while total < length:
        for attempt in range(60):
            spread = np.pi / 3 if attempt < 40 else np.pi / 2
            turn = np.clip(rng.normal(0.0, spread), -np.pi / 2, np.pi / 2)
            if attempt >= 55:  # a dead end: turn back
                turn = rng.uniform(-np.pi, np.pi)
            leg = rng.uniform(0.6, 2.0) if attempt < 50 else rng.uniform(0.15, 0.6)
            candidate = points[-1] + leg * np.array(
                [np.cos(heading + turn), np.sin(heading + turn)]
            )
            if _segment_free(space, points[-1], candidate):
                break
        else:
            return None
        heading += turn
        total += leg
        points.append(candidate)
    return np.asarray(points)


def _chaikin(points: np.ndarray, iterations: int = 4) -> np.ndarray:
    for _ in range(iterations):
        q = 0.75 * points[:-1] + 0.25 * points[1:]
        r = 0.25 * points[:-1] + 0.75 * points[1:]
        inner = np.stack([q, r], axis=1).reshape(-1, points.shape[1])
        points = np.concatenate([points[:1], inner, points[-1:]])
    return points


def _smooth_series(rng: np.random.Generator, count: int, sigma_frames: float) -> np.ndarray:
    """A zero-mean, unit-std random series, smooth over about ``sigma_frames`` frames."""
    padded = ndimage.gaussian_filter1d(rng.normal(size=count + 8), sigma_frames, mode="nearest")
    series = padded[4:-4]
    return (series - series.mean()) / max(series.std(), 1e-9)


def sample_trajectory(
    rng: np.random.Generator,
    space: FreeSpace,
    num_frames: int,
    step_range: tuple[float, float],
    height_range: tuple[float, float],
    yaw_amplitude: float,
    tilt_sigma: float,
    attempts: int = 30,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses (T, 4) = (x, y, z, yaw) and tilts (T, 2) = (pitch, roll), radians, of a smooth walk.

    Consecutive positions are ``step_range`` apart (metres, a per-sequence speed with 15 %
    per-frame variation); heights stay inside ``height_range``; the yaw is the travel direction
    plus a look-around of amplitude up to ``yaw_amplitude`` radians; the tilt is a smooth random
    series with standard deviation ``tilt_sigma`` radians (zeros for a level camera).
    """
    speed = rng.uniform(*step_range)
    steps = np.clip(speed * (1.0 + rng.uniform(-0.15, 0.15, max(num_frames - 1, 0))), *step_range)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    for _ in range(attempts):
        waypoints = _waypoints(rng, space, 1.3 * arc[-1] + 1.0)
        if waypoints is None:
            continue
        curve = _chaikin(waypoints)
        curve_length = np.sum(np.linalg.norm(np.diff(curve, axis=0), axis=1))
        if curve_length >= arc[-1] + 0.3 and np.all(space.contains(curve)):
            break
    else:
        raise RuntimeError("no collision-free smooth trajectory found; the room is too cluttered")
    dense = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    xy = np.stack([np.interp(arc, dense, curve[:, k]) for k in range(2)], axis=-1)
    ahead = np.stack([np.interp(arc + LOOKAHEAD, dense, curve[:, k]) for k in range(2)], axis=-1)
    behind = np.stack([np.interp(arc - LOOKAHEAD, dense, curve[:, k]) for k in range(2)], axis=-1)
    travel = ahead - behind
    heading = np.unwrap(np.arctan2(travel[:, 1], travel[:, 0]))
    heading = ndimage.gaussian_filter1d(heading, HEADING_SMOOTHING, mode="nearest")
    frames = np.arange(num_frames)
    look = (
        rng.uniform(0.3, 1.0)
        * yaw_amplitude
        * np.sin(2 * np.pi * frames / rng.uniform(15.0, 40.0) + rng.uniform(0, 2 * np.pi))
    )
    yaw = (heading + look + np.pi) % (2 * np.pi) - np.pi
    low, high = height_range
    margin = min(0.03, (high - low) / 4)
    base = rng.uniform(low + margin, high - margin)
    z = base + margin * np.sin(
        2 * np.pi * frames / rng.uniform(6.0, 12.0) + rng.uniform(0, 2 * np.pi)
    )
    poses = np.column_stack([xy, z, yaw])
    tilt = np.zeros((num_frames, 2))
    if tilt_sigma > 0:
        tilt = tilt_sigma * np.stack([_smooth_series(rng, num_frames, 2.0) for _ in range(2)], -1)
    return poses.astype(np.float32), tilt.astype(np.float32)
