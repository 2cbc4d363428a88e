"""An interactive 3D view of a localization run: a Rerun recording (``.rrd``) of the map, the
particles, the trajectories, the verdicts and the frames, opened with ``rerun F.rrd`` (the Rerun
viewer, ``pip install "jaxloc[viz]"`` installs ``rerun-sdk``).

One call writes a run: :func:`write_rerun` for SG2Loc (a scene graph, an
:class:`~jaxloc.sg2loc.SG2LocResult`, optionally the query's frames and the ground truth) and
:func:`write_drive_rerun` for an M2Loc drive (an instance map, a
:class:`~jaxloc.m2loc.DriveResult`). The ``log_*`` functions log one part each into an open
recording (:func:`rrd_recording`), for views of one's own.

It lives in :mod:`jaxloc.io` because an ``.rrd`` is a file written for a foreign tool, and it
reads both methods' results (the layer that may import ``jaxloc.sg2loc`` and ``jaxloc.m2loc``).

Entities (the world frame is the map's, z up, metres; each frame of the run is one step of the
``frame`` timeline, and of a ``time`` timeline when stamps are given):

* ``world/map/objects/<i>``: object i's mesh, coloured by its class (``class_ids``);
  ``world/map/graph``: the scene graph's edges between object centroids;
  ``world/map/instances``: an instance map's centroids, coloured by class;
* ``world/particles/round_<r>``: round r's particles after each frame's update (weight > 0),
  coloured from dark (light weight) to yellow (the heaviest); ``.../mle``: the round's estimate;
* ``world/trajectory/estimate`` and ``world/trajectory/gt``: the whole paths (the estimate's
  segments coloured by the verdict: green localized, red not), and ``.../current`` the frame's
  pose as an arrow along the heading;
* ``world/camera``: the camera at the estimated pose, ``world/camera/image`` its pinhole, with
  ``rgb`` and ``depth`` (metres) below it; ``world/scan/instances``: an M2Loc scan's instances
  placed by the estimated pose (or the ground truth where there is none);
* ``plots/localized``, ``plots/position_error_m``, ``plots/rotation_error_deg``: per frame.
"""

from __future__ import annotations

import colorsys
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from jaxloc.io.camera_recording import camera_pose_matrices

#: Colours of the verdict (RGB, 0-255): localized, not localized.
LOCALIZED_COLOR, NOT_LOCALIZED_COLOR = (40, 200, 80), (230, 50, 40)
#: Colour of the ground truth.
GT_COLOR = (150, 150, 150)


def require_rerun():
    """The ``rerun`` module; ModuleNotFoundError with one line telling how to install it."""
    try:
        import rerun
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            "writing a Rerun recording (.rrd) needs the rerun-sdk package: "
            'pip install "jaxloc[viz]"'
        ) from None
    return rerun


def class_colors(class_ids) -> np.ndarray:
    """(N, 3) uint8 colours of the (N,) class ids: one fixed colour per id (hues spaced by the
    golden ratio, so neighbouring ids differ), grey for ids < 0."""
    ids = np.asarray(class_ids, np.int64).reshape(-1)
    out = np.full((ids.size, 3), 128, np.uint8)
    for value in np.unique(ids[ids >= 0]):
        rgb = colorsys.hsv_to_rgb((value * 0.618033988749895) % 1.0, 0.65, 0.92)
        out[ids == value] = np.round(np.asarray(rgb) * 255)
    return out


def _class_ids(labels) -> np.ndarray | None:
    """Rerun's class ids (uint16) of class ids, or None where one does not fit."""
    labels = np.asarray(labels, np.int64)
    return labels.astype(np.uint16) if np.all((labels >= 0) & (labels < 2**16)) else None


def _verdict_colors(verdict) -> np.ndarray:
    return np.where(np.asarray(verdict, bool)[:, None], LOCALIZED_COLOR, NOT_LOCALIZED_COLOR)


@contextmanager
def rrd_recording(
    path: str | os.PathLike, application_id: str = "jaxloc", blueprint=None
) -> Iterator:
    """A ``rerun.RecordingStream`` saving to ``path`` (written atomically when the block ends:
    a temporary file in its folder, renamed over ``path``), its ``world`` frame z up; the viewer
    opens it with ``blueprint`` (a ``rerun.blueprint.Blueprint``, e.g. :func:`default_layout`;
    None: the viewer's own guess)."""
    rr = require_rerun()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    os.close(fd)
    rec = rr.RecordingStream(application_id)
    rec.save(tmp, default_blueprint=blueprint)
    try:
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        yield rec
        rec.flush()
        rec.disconnect()
        os.chmod(tmp, 0o644)  # as the other writers: mkstemp's file is readable by its owner only
        os.replace(tmp, path)
    except BaseException:
        rec.disconnect()
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def default_layout(
    bounds,
    *,
    focus=None,
    inside: bool = False,
    rgb: bool = False,
    depth: bool = False,
    errors: bool = False,
):
    """The layout a recording of :func:`write_rerun` or :func:`write_drive_rerun` opens with: the
    world in 3D, seen from above one side of the map, beside the camera's images and the
    per-frame plots.

    Args:
        bounds: (2, 3) the map's corners (world frame, metres): the 3D view looks at their centre
            from a distance that shows them whole.
        focus: (3,) the point the 3D view looks at (default: the bounds' centre), e.g. the
            trajectory's centre.
        inside: look from inside the bounds, from the top corner farthest from ``focus`` (a room,
            whose walls and ceiling would hide the rest), instead of from above one side (a drive).
        rgb: whether the recording holds the camera's colour images (a 2D view).
        depth: whether it holds the camera's depth images (a 2D view).
        errors: whether it holds the position and rotation errors (a ground truth).

    Returns:
        A ``rerun.blueprint.Blueprint``.
    """
    require_rerun()
    import rerun.blueprint as rrb

    low, high = np.asarray(bounds, np.float64)
    centre = (low + high) / 2 if focus is None else np.asarray(focus, np.float64)
    size = max(float(np.max(high[:2] - low[:2])), 1.0)
    position = centre + np.array([0.0, -0.9, 1.1]) * size
    if inside:  # the top corner farthest from the focus, inset a little
        corners = np.array([[x, y, 0.9] for x in (0.05, 0.95) for y in (0.05, 0.95)])
        corners = low + corners * (high - low)
        position = corners[np.argmax(np.linalg.norm(corners[:, :2] - centre[:2], axis=1))]
    eye = rrb.EyeControls3D(position=position, look_target=centre, eye_up=(0, 0, 1))
    world = rrb.Spatial3DView(origin="world", name="map, particles, trajectories", eye_controls=eye)
    image = "world/camera/image"
    side = [rrb.Spatial2DView(origin=image, contents="$origin/rgb", name="colour")] if rgb else []
    side += [rrb.Spatial2DView(origin=image, contents="$origin/depth", name="depth")] * depth
    plots = ["localized"] + ["position_error_m", "rotation_error_deg"] * errors
    side.append(rrb.Tabs(*(rrb.TimeSeriesView(origin=f"plots/{p}", name=p) for p in plots)))
    return rrb.Blueprint(rrb.Horizontal(world, rrb.Vertical(*side), column_shares=[3, 2]))


def _set_frame(rec, t: int, timestamps) -> None:
    rec.set_time("frame", sequence=int(t))
    if timestamps is not None:
        rec.set_time("time", timestamp=float(timestamps[t]))


def log_scene_graph(rec, scene, entity: str = "world/map") -> None:
    """Log a :class:`~jaxloc.SceneGraph`'s object meshes, each coloured by its class, and its
    edges between the objects' centroids (static: the same at every frame)."""
    rr = require_rerun()
    triangles = np.asarray(scene.triangles, np.float32)
    owner = np.asarray(scene.triangle_object)
    labels = np.asarray(scene.labels)
    colors = class_colors(labels)
    centroids = np.zeros((labels.size, 3))
    for index in range(scene.num_objects):
        vertices = triangles[owner == index].reshape(-1, 3)
        if not len(vertices):
            continue
        centroids[index] = vertices.mean(0)
        rec.log(
            f"{entity}/objects/{index}",
            rr.Mesh3D(
                vertex_positions=vertices,
                triangle_indices=np.arange(len(vertices), dtype=np.uint32).reshape(-1, 3),
                vertex_colors=np.repeat(colors[index][None], len(vertices), 0),
                class_ids=_class_ids(labels[index : index + 1]),
            ),
            static=True,
        )
    edges = np.asarray(scene.edges)
    edges = edges[(edges >= 0).all(1) & (edges < scene.num_objects).all(1)]
    if len(edges):
        rec.log(f"{entity}/graph", rr.LineStrips3D(centroids[edges], radii=0.01), static=True)


def log_instance_map(rec, instance_map, entity: str = "world/map/instances") -> None:
    """Log an instance map's centroids coloured by class (static): an
    :class:`~jaxloc.io.InstanceMap` (``points`` (N, 3) metres, ``labels`` (N,) class ids) or a
    :class:`~jaxloc.m2loc.TripletMap` (its vertices plus ``origin``, its classes' ids)."""
    rr = require_rerun()
    points, labels = _map_points(instance_map)
    rec.log(
        entity,
        rr.Points3D(
            points,
            colors=class_colors(labels),
            class_ids=_class_ids(labels),
            radii=rr.Radius.ui_points(3.0),
        ),
        static=True,
    )


def _map_points(instance_map) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world-frame centroids and (N,) class ids of an instance map or a triplet map."""
    if hasattr(instance_map, "labels"):
        return np.asarray(instance_map.points), np.asarray(instance_map.labels)
    points = np.asarray(instance_map.points, np.float64) + np.asarray(instance_map.origin)
    classes = np.asarray(instance_map.config.descriptor.classes)
    return points, classes[np.asarray(instance_map.classes)]


def _weight_colors(weights: np.ndarray) -> np.ndarray:
    """Dark blue (light) to yellow (the heaviest) of (N,) weights > 0."""
    w = weights / weights.max()
    dark, bright = np.array([40, 30, 110]), np.array([250, 220, 30])
    return np.round(dark + w[:, None] * (bright - dark)).astype(np.uint8)


def _arrows(poses: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """(origins, vectors) of (T, 4) yaw poses (x, y, z, yaw) or (T, 4, 4) matrices (their x
    axis: the heading of a LiDAR scan or a body frame)."""
    poses = np.asarray(poses, np.float64)
    if poses.ndim == 3:
        return poses[:, :3, 3], length * poses[:, :3, 0]
    heading = np.stack([np.cos(poses[:, 3]), np.sin(poses[:, 3]), np.zeros(len(poses))], -1)
    return poses[:, :3], length * heading


def log_particles(
    rec,
    result,
    entity: str = "world/particles",
    timestamps=None,
    max_particles: int | None = None,
) -> None:
    """Log an :class:`~jaxloc.sg2loc.SG2LocResult`'s particles per round and frame
    (``result.particles`` (R, T, N, 4) with ``result.particle_weights`` (R, T, N); those of
    weight 0 are inactive slots and left out) and each round's estimate
    (``result.round_mle`` (R, T, 4)) as an arrow; ``max_particles`` keeps the heaviest."""
    rr = require_rerun()
    particles = np.asarray(result.particles, np.float64)
    weights = np.asarray(result.particle_weights, np.float64)
    mle = np.asarray(result.round_mle, np.float64)
    rounds, frames = particles.shape[:2]
    for t in range(frames):
        _set_frame(rec, t, timestamps)
        for r in range(rounds):
            active = np.flatnonzero(weights[r, t] > 0)
            if max_particles is not None and active.size > max_particles:
                active = active[np.argsort(weights[r, t, active])[-max_particles:]]
            if active.size:
                rec.log(
                    f"{entity}/round_{r}",
                    rr.Points3D(
                        particles[r, t, active, :3],
                        colors=_weight_colors(weights[r, t, active]),
                        radii=0.03,
                    ),
                )
            origins, vectors = _arrows(mle[r, t][None], 0.4)
            rec.log(f"{entity}/round_{r}/mle", rr.Arrows3D(origins=origins, vectors=vectors))


def log_trajectory(
    rec,
    poses,
    poses_gt=None,
    verdict=None,
    entity: str = "world/trajectory",
    timestamps=None,
    labels=None,
    has_pose=None,
    has_gt=None,
) -> None:
    """Log an estimated trajectory, the ground truth and the per-frame verdict.

    Args:
        rec: the recording (:func:`rrd_recording`).
        poses: (T, 4) yaw poses (x, y, z, yaw; SG2Loc) or (T, 4, 4) ``T_map_frame`` (M2Loc), in
            the map frame, metres and radians.
        poses_gt: the ground truth, the same shape, or None.
        verdict: (T,) bool, whether each estimate is to be acted on (default all True); frames
            without one are drawn red and kept out of the error plots.
        entity: the trajectory's entity path.
        timestamps: (T,) seconds for the ``time`` timeline, or None.
        labels: (T,) text shown on each frame's arrow (e.g. an M2Loc status), or None.
        has_pose: (T,) bool, the frames ``poses`` holds an estimate for (default all; an M2Loc
            scan that did not localize has none): the path skips the others.
        has_gt: (T,) bool, the frames ``poses_gt`` holds a pose for (default all).
    """
    rr = require_rerun()
    poses = np.asarray(poses, np.float64)
    every = np.ones(len(poses), bool)
    verdict = every if verdict is None else np.asarray(verdict, bool)
    has_pose = every if has_pose is None else np.asarray(has_pose, bool)
    origins, vectors = _arrows(poses, 0.5)
    colors = _verdict_colors(verdict)
    joined = np.flatnonzero(has_pose[:-1] & has_pose[1:])
    if joined.size:
        segments = np.stack([origins[joined], origins[joined + 1]], 1)
        rec.log(
            f"{entity}/estimate", rr.LineStrips3D(segments, colors=colors[joined + 1]), static=True
        )
    gt_origins = gt_vectors = None
    if poses_gt is not None:
        has_gt = every if has_gt is None else np.asarray(has_gt, bool)
        gt_origins, gt_vectors = _arrows(np.asarray(poses_gt, np.float64), 0.5)
        strip = gt_origins[has_gt]
        rec.log(f"{entity}/gt", rr.LineStrips3D([strip], colors=[GT_COLOR]), static=True)
    for t in range(len(poses)):
        _set_frame(rec, t, timestamps)
        rec.log("plots/localized", rr.Scalars([float(verdict[t])]))
        if has_pose[t]:
            text = None if labels is None else [str(labels[t])]
            rec.log(
                f"{entity}/estimate/current",
                rr.Arrows3D(origins=origins[t : t + 1], vectors=vectors[t : t + 1],
                            colors=colors[t : t + 1], labels=text),
            )  # fmt: skip
        else:
            rec.log(f"{entity}/estimate/current", rr.Clear(recursive=False))
        if gt_origins is None or not has_gt[t]:
            continue
        rec.log(
            f"{entity}/gt/current",
            rr.Arrows3D(origins=gt_origins[t : t + 1], vectors=gt_vectors[t : t + 1],
                        colors=[GT_COLOR]),
        )  # fmt: skip
        if verdict[t] and has_pose[t]:
            error = np.linalg.norm(origins[t] - gt_origins[t])
            turn = np.arctan2(np.cross(vectors[t], gt_vectors[t])[2], vectors[t] @ gt_vectors[t])
            rec.log("plots/position_error_m", rr.Scalars([float(error)]))
            rec.log("plots/rotation_error_deg", rr.Scalars([float(abs(np.degrees(turn)))]))


def log_camera_frames(
    rec, sequence, T_world_cam, entity: str = "world/camera", timestamps=None, jpeg_quality=90
) -> None:
    """Log a query :class:`~jaxloc.sg2loc.FrameSequence`'s colour and depth images on its
    pinhole camera, placed at the (T, 4, 4) camera-to-world poses ``T_world_cam`` (OpenCV
    axes); colour as JPEG of ``jpeg_quality`` (None: raw pixels)."""
    rr = require_rerun()
    camera = sequence.camera
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]], np.float32)
    rec.log(
        f"{entity}/image",
        rr.Pinhole(image_from_camera=K, resolution=[camera.width, camera.height]),
        static=True,
    )
    rgb = None if sequence.rgb is None else np.asarray(sequence.rgb)
    depth = None if sequence.depth is None else np.asarray(sequence.depth, np.float32)
    T_world_cam = np.asarray(T_world_cam, np.float64)
    for t in range(len(T_world_cam)):
        _set_frame(rec, t, timestamps)
        rec.log(entity, rr.Transform3D(translation=T_world_cam[t, :3, 3],
                                       mat3x3=T_world_cam[t, :3, :3]))  # fmt: skip
        if rgb is not None:
            image = rr.Image(np.round(np.clip(rgb[t], 0, 1) * 255).astype(np.uint8))
            if jpeg_quality is not None:
                image = image.compress(jpeg_quality=jpeg_quality)
            rec.log(f"{entity}/image/rgb", image)
        if depth is not None:
            rec.log(f"{entity}/image/depth", rr.DepthImage(depth[t], meter=1.0))


def write_rerun(
    path: str | os.PathLike,
    scene,
    result,
    sequence=None,
    poses_gt=None,
    *,
    timestamps=None,
    max_particles: int | None = None,
    application_id: str = "jaxloc",
) -> Path:
    """Write an SG2Loc run as a Rerun recording (``.rrd``; see the module docstring).

    Args:
        path: the ``.rrd`` file to create or replace.
        scene: the map, a :class:`~jaxloc.SceneGraph`.
        result: the :class:`~jaxloc.sg2loc.SG2LocResult` of :func:`jaxloc.sg2loc.localize`,
            or the stacked :class:`~jaxloc.sg2loc.online.Estimate` of
            :func:`jaxloc.sg2loc.online.filter_sequence` (its ``pose``; no particles).
        sequence: the query (:class:`~jaxloc.sg2loc.FrameSequence`) or the
            :class:`~jaxloc.io.CameraRecording` it came from (then its ground truth and
            timestamps are used unless given): its frames are logged, with the camera at the
            estimated pose and the frames' tilt. None: no frames.
        poses_gt: (T, 4) ground-truth yaw poses (x, y, z, yaw), or None.
        timestamps: (T,) seconds of the frames for a ``time`` timeline, or None.
        max_particles: the heaviest particles kept per round and frame (None: all).
        application_id: the recording's application id in the viewer.

    Returns:
        ``path``.

    Raises:
        ModuleNotFoundError: without rerun-sdk (``pip install "jaxloc[viz]"``).
    """
    if sequence is not None and hasattr(sequence, "sequence"):  # a CameraRecording
        poses_gt = sequence.poses_gt if poses_gt is None else poses_gt
        timestamps = sequence.timestamps if timestamps is None else timestamps
        sequence = sequence.sequence
    poses = np.asarray(result.poses if hasattr(result, "poses") else result.pose, np.float64)
    owner = np.asarray(scene.triangle_object)
    vertices = np.asarray(scene.triangles)[(owner >= 0) & (owner < scene.num_objects)]
    vertices = np.concatenate([vertices.reshape(-1, 3), poses[:, :3]])
    layout = default_layout(
        [vertices.min(0), vertices.max(0)],
        focus=poses[:, :3].mean(0),
        inside=True,
        rgb=sequence is not None and sequence.rgb is not None,
        depth=sequence is not None and sequence.depth is not None,
        errors=poses_gt is not None,
    )
    with rrd_recording(path, application_id, layout) as rec:
        log_scene_graph(rec, scene)
        if hasattr(result, "particles"):
            log_particles(rec, result, timestamps=timestamps, max_particles=max_particles)
        log_trajectory(rec, poses, poses_gt, np.asarray(result.localized), timestamps=timestamps)
        if sequence is not None:
            T_world_cam = camera_pose_matrices(poses, np.asarray(sequence.tilt))
            log_camera_frames(rec, sequence, T_world_cam, timestamps=timestamps)
    return Path(path)


def write_drive_rerun(
    path: str | os.PathLike,
    instance_map,
    drive,
    poses_gt=None,
    *,
    has_gt=None,
    timestamps=None,
    application_id: str = "jaxloc",
) -> Path:
    """Write an M2Loc drive as a Rerun recording (``.rrd``; see the module docstring).

    Args:
        path: the ``.rrd`` file to create or replace.
        instance_map: the map: an :class:`~jaxloc.io.InstanceMap` or a
            :class:`~jaxloc.m2loc.TripletMap`.
        drive: the :class:`~jaxloc.m2loc.DriveResult` of :func:`jaxloc.m2loc.localize_drive`:
            its (N, 4, 4) ``T_map_scan`` poses where ``valid``, each scan's status (the arrow's
            label) and instances (placed by the pose).
        poses_gt: (N, 4, 4) ground-truth ``T_map_scan``, or None (a
            :class:`~jaxloc.io.LidarRecording`'s ``poses``).
        has_gt: (N,) bool, the scans ``poses_gt`` holds a pose for (default all; a recording's
            ``has_pose``).
        timestamps: (N,) seconds of the scans for a ``time`` timeline, or None.
        application_id: the recording's application id in the viewer.

    Returns:
        ``path``.

    Raises:
        ModuleNotFoundError: without rerun-sdk (``pip install "jaxloc[viz]"``).
    """
    from jaxloc.m2loc import TrackStatus

    rr = require_rerun()
    valid = np.asarray(drive.valid, bool)
    poses = np.asarray(drive.poses, np.float64)
    gt = None if poses_gt is None else np.asarray(poses_gt, np.float64)
    names = [TrackStatus(int(s)).name.lower() for s in np.asarray(drive.status)]
    corners = np.concatenate([_map_points(instance_map)[0], poses[valid, :3, 3]])
    layout = default_layout([corners.min(0), corners.max(0)], errors=gt is not None)
    with rrd_recording(path, application_id, layout) as rec:
        log_instance_map(rec, instance_map)
        has_gt = np.ones(len(poses), bool) if has_gt is None else np.asarray(has_gt, bool)
        log_trajectory(rec, poses, gt, valid, timestamps=timestamps, labels=names,
                       has_pose=valid, has_gt=has_gt)  # fmt: skip
        for t, step in enumerate(drive.steps):
            pose = poses[t] if valid[t] else (gt[t] if gt is not None and has_gt[t] else None)
            if pose is None or not len(step.instances.points):
                continue
            _set_frame(rec, t, timestamps)
            points = np.asarray(step.instances.points, np.float64) @ pose[:3, :3].T + pose[:3, 3]
            labels = np.asarray(step.instances.labels)
            rec.log(
                "world/scan/instances",
                rr.Points3D(
                    points,
                    colors=class_colors(labels),
                    class_ids=_class_ids(labels),
                    radii=rr.Radius.ui_points(6.0),
                ),
            )
    return Path(path)
