"""Configuration of the synthetic indoor world: rooms, scene changes, trajectories, sensors.

Frozen dataclasses, validated on construction (``ValueError`` for out-of-range values). Lengths
in metres, angles in radians unless a name says degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jaxloc.camera import Camera


def _check_range(name: str, value, low: float = -np.inf, high: float = np.inf) -> None:
    if len(value) != 2 or not (low <= value[0] <= value[1] <= high):
        raise ValueError(f"{name} must be a (min, max) pair within [{low}, {high}], got {value}")


@dataclass(frozen=True)
class RoomConfig:
    """How rooms are generated. Lengths in metres.

    Attributes:
        length_range, width_range, height_range: room extent along x, y and z.
        num_objects: (min, max) furniture objects; the upper end is reached in rooms of about
            50 m^2 (the count drawn is ``U(min, min(max, min + area / 2))``).
        vertex_range: (min, max) vertices per object mesh.
        embedding_dim: object embedding dimension d.
        class_similarity: s, the expected cosine between two objects of one class.
        class_seed: seed of the class vectors (shared by every room).
        walkway_fraction: a central rectangle of this fraction of each side is kept free of
            floor furniture so the camera can move.
    """

    length_range: tuple[float, float] = (4.0, 10.0)
    width_range: tuple[float, float] = (4.0, 8.0)
    height_range: tuple[float, float] = (2.6, 3.0)
    num_objects: tuple[int, int] = (15, 40)
    vertex_range: tuple[int, int] = (400, 1000)
    embedding_dim: int = 400
    class_similarity: float = 0.5
    class_seed: int = 0
    walkway_fraction: float = 0.35

    def __post_init__(self):
        _check_range("length_range", self.length_range, 3.0)
        _check_range("width_range", self.width_range, 3.0)
        _check_range("height_range", self.height_range, 2.3)
        _check_range("num_objects", self.num_objects, 0)
        _check_range("vertex_range", self.vertex_range, 100)
        if self.embedding_dim < 2:
            raise ValueError(f"embedding_dim must be >= 2, got {self.embedding_dim}")
        if not 0.0 <= self.class_similarity <= 1.0:
            raise ValueError(f"class_similarity must be in [0, 1], got {self.class_similarity}")
        if not 0.0 <= self.walkway_fraction <= 0.6:
            raise ValueError(f"walkway_fraction must be in [0, 0.6], got {self.walkway_fraction}")


@dataclass(frozen=True)
class ChangeConfig:
    """Scene changes between the map and the query.

    Attributes:
        fraction: fraction of the furniture objects changed (rounded to a count; only movable
            classes are changed, so doors, windows and radiators stay).
        move_probability: a changed object is moved (floor objects shift 0.3-1.0 m and turn up
            to 45 degrees, wall-hung ones slide along the wall) with this probability, else
            removed; a move that finds no free spot removes the object.
    """

    fraction: float = 0.1
    move_probability: float = 0.5

    def __post_init__(self):
        if not 0.0 <= self.fraction <= 1.0:
            raise ValueError(f"fraction must be in [0, 1], got {self.fraction}")
        if not 0.0 <= self.move_probability <= 1.0:
            raise ValueError(f"move_probability must be in [0, 1], got {self.move_probability}")


@dataclass(frozen=True)
class TrajectoryConfig:
    """Camera trajectories (metres, radians).

    Attributes:
        height_range: camera height above the floor.
        step_range: distance between consecutive frames.
        yaw_amplitude: largest look-around angle added to the direction of travel.
        tilt_sigma: standard deviation of a smooth random pitch and roll (0 = level camera).
        wall_clearance, object_clearance: the camera keeps this far from walls and from floor
            furniture (of the map and of the changed scene).
    """

    height_range: tuple[float, float] = (1.4, 1.9)
    step_range: tuple[float, float] = (0.1, 0.3)
    yaw_amplitude: float = float(np.deg2rad(45.0))
    tilt_sigma: float = 0.0
    wall_clearance: float = 0.5
    object_clearance: float = 0.35

    def __post_init__(self):
        _check_range("height_range", self.height_range, 0.1)
        _check_range("step_range", self.step_range, 0.0)
        for name in ("yaw_amplitude", "tilt_sigma", "wall_clearance", "object_clearance"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


#: The sensor depth models of :class:`SensorConfig`.
DEPTH_MODELS = ("relative", "kinect")


@dataclass(frozen=True)
class SensorConfig:
    """Camera, patch grid and sensor noise. The defaults are the realistic (hard) setting.

    Attributes:
        width, height: image size in pixels (the SG2Loc reference uses 960x540).
        hfov_deg: horizontal field of view in degrees.
        patch_rows, patch_cols: patch grid (the reference uses 9 x 16 patches of 60 px).
        confusion_rate: probability that a patch's embedding comes from another object.
        cosine_range: (min, max) cosine between a patch embedding and its source object.
        depth_noise: relative standard deviation of depth (0.02 = 2 %) of the ``"relative"``
            depth model.
        depth_model: ``"relative"`` (noise proportional to depth, blob holes) or ``"kinect"``
            (a structured-light sensor: axial noise ``0.0012 + 0.0019 (z - 0.4)^2`` metres,
            Nguyen et al. 2012, no depth beyond 4.5 m or across depth edges, blob holes;
            ``depth_noise`` unused).
        hole_rate: fraction of depth pixels set to 0 (invalid) in blobs.
        rgb_noise: standard deviation of per-pixel colour noise (colours in [0, 1]).
        exposure_sigma: standard deviation of the log exposure gain per frame.
        ego_translation_sigma: ego-motion noise per frame on each of dx, dy, dz (metres).
        ego_yaw_sigma: ego-motion noise per frame on dyaw (radians).
    """

    width: int = 960
    height: int = 540
    hfov_deg: float = 60.0
    patch_rows: int = 9
    patch_cols: int = 16
    confusion_rate: float = 0.2
    cosine_range: tuple[float, float] = (0.7, 0.9)
    depth_noise: float = 0.02
    depth_model: str = "relative"
    hole_rate: float = 0.1
    rgb_noise: float = 0.02
    exposure_sigma: float = 0.15
    ego_translation_sigma: float = 0.02
    ego_yaw_sigma: float = float(np.deg2rad(1.0))

    def __post_init__(self):
        if self.width < self.patch_cols or self.height < self.patch_rows or self.patch_rows < 1:
            raise ValueError(
                f"image {self.width}x{self.height} must hold the {self.patch_rows}x"
                f"{self.patch_cols} patch grid, a pixel per patch at least: want width >= "
                f"{self.patch_cols} and height >= {self.patch_rows}"
            )
        if not 0 < self.hfov_deg < 180:
            raise ValueError(f"hfov_deg must be in (0, 180), got {self.hfov_deg}")
        _check_range("cosine_range", self.cosine_range, -1.0, 1.0)
        if self.depth_model not in DEPTH_MODELS:
            raise ValueError(f"depth_model must be one of {DEPTH_MODELS}, got {self.depth_model!r}")
        for name in ("confusion_rate", "hole_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in (
            "depth_noise",
            "rgb_noise",
            "exposure_sigma",
            "ego_translation_sigma",
            "ego_yaw_sigma",
        ):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    def camera(self) -> Camera:
        """The pinhole camera: square pixels, centred principal point."""
        return Camera.from_fov(self.width, self.height, self.hfov_deg)


@dataclass(frozen=True)
class EpisodeConfig:
    """Everything :func:`make_episode` draws from: room, changes, trajectory and sensors."""

    room: RoomConfig = field(default_factory=RoomConfig)
    changes: ChangeConfig = field(default_factory=ChangeConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
