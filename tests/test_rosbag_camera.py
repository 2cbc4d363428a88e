"""Camera recordings from ROS bags: a synthetic episode written as a ScanNet export folder and as
bags (ROS 1, ROS 2 sqlite3, ROS 2 MCAP, a bare .mcap; written with rosbags' own writers,
tests/_rosbag_fixtures.py) opens to the same query (images, depth, intrinsics, ego-motion, ground
truth, patch embeddings); bad bags are one line naming the bag and the topic."""

from __future__ import annotations

import dataclasses
import io
import json
import shutil

import numpy as np
import pytest
import trimesh
from _rosbag_fixtures import KINDS, Messages, write_bag
from PIL import Image

from jaxloc.cli import main
from jaxloc.io import ClassEmbeddings
from jaxloc.io.camera_recording import open_camera_recording
from jaxloc.io.camera_sequence import read_camera_sequence
from jaxloc.io.poses import write_tum
from jaxloc.io.rosbag_camera import is_bag, read_bag_camera_sequence
from jaxloc.io.scene_map import save_scene
from jaxloc.scene import SceneGraph
from jaxloc.synthetic import indoor
from jaxloc.synthetic.indoor.export import write_scannet_export

FRAMES = 4
T0 = 1_700_000_000_000_000_123  # ns: an epoch stamp with nanoseconds
PERIOD = 100_000_000  # 10 Hz
STAMPS = [T0 + t * PERIOD for t in range(FRAMES)]
COLOR, DEPTH = "/camera/color/image_raw", "/camera/depth/image_rect_raw"
CAM_FRAME = "camera_color_optical_frame"
#: base_link -> camera optical frame (OpenCV axes: z forward along base x, x right, y down).
T_BASE_CAM = np.array([[0.0, 0, 1, 0.1], [-1, 0, 0, 0.0], [0, -1, 0, 0.3], [0, 0, 0, 1]])
#: odom -> world: the odometry's own origin (a yaw and a shift: the ego-motion does not change).
T_ODOM_WORLD = np.array([[0.0, -1, 0, 2.0], [1, 0, 0, -1.0], [0, 0, 1, 0.0], [0, 0, 0, 1]])
CLASS_IDS = (1, 2, 5)


@pytest.fixture(scope="module")
def episode_folder(tmp_path_factory):
    """(root, the episode's export folder, its pose matrices, label images) of 4 frames."""
    config = indoor.EpisodeConfig(
        sensor=indoor.SensorConfig(width=64, height=48),
        trajectory=indoor.TrajectoryConfig(tilt_sigma=0.05),
    )
    episode = indoor.make_episode(5, FRAMES, config)
    root = tmp_path_factory.mktemp("bags")
    folder = write_scannet_export(episode, root / "export")
    save_scene(episode.scene, root / "map.npz")  # the map localize-camera reads
    poses = np.stack([np.loadtxt(folder / "pose" / f"{t}.txt") for t in range(FRAMES)])
    labels = np.random.default_rng(0).choice([0, *CLASS_IDS], size=(FRAMES, 48, 64))
    return root, folder, poses, labels.astype(np.uint16)


def _odometry_samples(poses):
    """(stamp, T_odom_base) at each frame and half-way between (slerp), one before, one after."""
    from scipy.spatial.transform import Rotation, Slerp

    T_odom_base = T_ODOM_WORLD @ poses @ np.linalg.inv(T_BASE_CAM)
    times = np.asarray(STAMPS, np.float64) - T0
    slerp = Slerp(times, Rotation.from_matrix(T_odom_base[:, :3, :3]))
    at = np.concatenate([[-PERIOD], np.arange(2 * FRAMES - 1) * PERIOD / 2, [times[-1] + PERIOD]])
    inside = np.clip(at, times[0], times[-1])
    out = np.repeat(np.eye(4)[None], len(at), 0)
    out[:, :3, :3] = slerp(inside).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(inside, times, T_odom_base[:, k, 3])
    return [(T0 + int(a), T) for a, T in zip(at, out, strict=True)]


def camera_messages(
    folder, poses, kind, *, colour="jpeg", odometry="odom", labels=None, depth="16UC1",
    label_encoding="mono16",
):  # fmt: skip
    """The episode's messages: colour (JPEG CompressedImage with the folder's bytes, or raw
    ``colour`` encoding), depth (the folder's millimetres as 16UC1, or metres as 32FC1),
    CameraInfo, /tf_static, and odometry ("odom": an Odometry topic; "tf": /tf; None)."""
    m, out = Messages(kind), []
    K = np.loadtxt(folder / "intrinsic" / "intrinsic_color.txt")
    for t, stamp in enumerate(STAMPS):
        jpeg = (folder / "color" / f"{t}.jpg").read_bytes()
        if colour == "jpeg":
            msg = m.compressed(stamp, CAM_FRAME, jpeg)
            out.append((COLOR + "/compressed", "sensor_msgs/msg/CompressedImage", stamp, msg))
        else:
            rgb = np.asarray(Image.open(folder / "color" / f"{t}.jpg").convert("RGB"))
            pixels = {
                "rgb8": rgb,
                "bgr8": rgb[..., ::-1],
                "mono8": rgb[..., 0],
                "rgba8": np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)]),
                "bgra8": np.dstack([rgb[..., ::-1], np.zeros(rgb.shape[:2], np.uint8)]),
            }
            out.append((COLOR, "sensor_msgs/msg/Image", stamp,
                        m.image(stamp, CAM_FRAME, pixels[colour], colour)))  # fmt: skip
        mm = np.asarray(Image.open(folder / "depth" / f"{t}.png")).astype(np.uint16)
        out.append(_depth_message(m, stamp + 1000, mm, depth, bigendian=t % 2 == 1))
        out.append(("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", stamp,
                    m.camera_info(stamp, CAM_FRAME, K, (64, 48))))  # fmt: skip
        if labels is not None:
            out.append(("/segmentation", "sensor_msgs/msg/Image", stamp,
                        m.image(stamp, CAM_FRAME, labels[t].astype(np.uint16 if label_encoding
                                == "mono16" else np.uint8), label_encoding)))  # fmt: skip
    static = m.tf([(0, "base_link", CAM_FRAME, T_BASE_CAM)])
    out.append(("/tf_static", "tf2_msgs/msg/TFMessage", T0 - PERIOD, static))
    for stamp, T in _odometry_samples(poses) if odometry else []:
        if odometry == "odom":
            msg = m.odometry(stamp, "odom", "base_link", T)
            out.append(("/odom", "nav_msgs/msg/Odometry", stamp, msg))
        else:
            msg = m.tf([(stamp, "odom", "base_link", T)])
            out.append(("/tf", "tf2_msgs/msg/TFMessage", stamp, msg))
    return out


#: compressed_depth_image_transport's defaults: inverse-depth quantization and the farthest depth.
DEPTH_QUANTIZATION, DEPTH_MAX = 100.0, 10.0


def _depth_message(m, stamp, mm, depth, bigendian=False):
    """The depth topic's message of ``mm`` millimetres: an ``Image`` (``depth`` "16UC1", or
    "32FC1" in metres) or a PNG ``compressedDepth`` ``CompressedImage`` ("16UC1 compressedDepth",
    "32FC1 compressedDepth"), coded as image_transport's compressed_depth plugin documents it."""
    if depth == "16UC1":
        return (
            DEPTH,
            "sensor_msgs/msg/Image",
            stamp,
            m.image(stamp, CAM_FRAME, mm, "16UC1", bigendian),
        )
    metres = mm.astype(np.float32) / 1000
    if depth == "32FC1":
        return DEPTH, "sensor_msgs/msg/Image", stamp, m.image(stamp, CAM_FRAME, metres, "32FC1")
    encoding = depth.split()[0]
    a = DEPTH_QUANTIZATION * (DEPTH_QUANTIZATION + 1)
    b = 1 - a / DEPTH_MAX
    if encoding == "16UC1":
        pixels = mm
    else:  # quantized inverse depth, truncated as C++ converts float to unsigned short
        with np.errstate(divide="ignore"):
            pixels = np.where((metres > 0) & (metres < DEPTH_MAX), a / metres + b, 0)
        pixels = pixels.astype(np.uint16)
    png = io.BytesIO()
    Image.fromarray(pixels.astype(np.uint16)).save(png, format="PNG")
    header = np.array([0], "<i4").tobytes() + np.array([a, b], "<f4").tobytes()
    message = m.compressed(
        stamp, CAM_FRAME, header + png.getvalue(), f"{encoding}; compressedDepth png"
    )
    return DEPTH + "/compressedDepth", "sensor_msgs/msg/CompressedImage", stamp, message


def _embeddings_by_stamp(folder, target):
    target.mkdir(exist_ok=True)
    for t, stamp in enumerate(STAMPS):
        shutil.copy(folder / "embeddings" / f"{t}.npy", target / f"{stamp}.npy")
    return target


def _assert_same_query(bag_rec, folder_rec, rgb_exact=True, depth_atol=0.0):
    a, b = bag_rec.sequence, folder_rec.sequence
    assert bag_rec.format == "rosbag" and bag_rec.frame_ids == folder_rec.frame_ids
    assert a.camera == b.camera and bag_rec.camera_native == folder_rec.camera_native
    np.testing.assert_array_equal(a.patch_embeddings, b.patch_embeddings)
    np.testing.assert_allclose(a.depth, b.depth, rtol=0, atol=depth_atol)
    if rgb_exact:
        np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_allclose(a.ego_motion, b.ego_motion, atol=1e-6)  # float32
    np.testing.assert_allclose(a.tilt, b.tilt, atol=1e-6)
    stamps = np.asarray(STAMPS)[list(bag_rec.frame_ids)]
    np.testing.assert_array_equal(bag_rec.timestamps, stamps / 1e9)


@pytest.mark.parametrize("kind", KINDS)
def test_a_bag_opens_to_the_folders_query(episode_folder, kind, tmp_path):
    """JPEG colour, 16UC1 depth (little- and big-endian), CameraInfo, Odometry of base_link
    carried to the camera by /tf_static and interpolated, embeddings by stamp, TUM ground truth."""
    root, folder, poses, _ = episode_folder
    bag = write_bag(tmp_path / "rec", kind, camera_messages(folder, poses, kind))
    assert is_bag(bag)
    write_tum(tmp_path / "gt.tum", poses, np.asarray(STAMPS, np.int64))
    recording = read_bag_camera_sequence(
        bag, gt=tmp_path / "gt.tum", embeddings_dir=_embeddings_by_stamp(folder, tmp_path / "e")
    )
    reference = read_camera_sequence(folder)
    _assert_same_query(recording, reference)
    np.testing.assert_allclose(recording.poses_gt, reference.poses_gt, atol=1e-6)
    np.testing.assert_allclose(recording.tilt_gt, reference.tilt_gt, atol=1e-6)
    resized = read_bag_camera_sequence(bag, width=32, odometry_topic="/odom",
                                       embeddings_dir=tmp_path / "e", step=2)  # fmt: skip
    _assert_same_query(resized, read_camera_sequence(folder, width=32, step=2), rgb_exact=False)


@pytest.mark.parametrize("depth", ["16UC1 compressedDepth", "32FC1 compressedDepth"])
def test_compressed_depth_reads_as_the_raw_depth(episode_folder, depth, tmp_path):
    """PNG ``compressedDepth`` depth (image_transport's compressed_depth plugin): 16UC1 gives the
    folder's millimetres exactly; 32FC1, coded as quantized inverse depth, within one quantization
    step (``d**2 / a`` at depth ``d``)."""
    root, folder, poses, _ = episode_folder
    bag = write_bag(tmp_path / "rec", "mcap", camera_messages(folder, poses, "mcap", depth=depth))
    embeddings = _embeddings_by_stamp(folder, tmp_path / "e")
    recording = read_bag_camera_sequence(bag, embeddings_dir=embeddings)
    reference = read_camera_sequence(folder)
    far = float(np.max(reference.sequence.depth))
    step = (
        0.0 if depth.startswith("16") else far**2 / (DEPTH_QUANTIZATION * (DEPTH_QUANTIZATION + 1))
    )
    assert 0 < step < 0.01 or depth.startswith("16")
    _assert_same_query(recording, reference, depth_atol=step + 1e-6)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8"])
def test_raw_colour_tf_odometry_and_label_topic(episode_folder, encoding, tmp_path):
    """Raw colour in every encoding, 32FC1 depth (metres), the /tf tree as odometry, label images
    from a mono16 or mono8 topic made into embeddings as the folder's label images are, a
    PoseStamped ground-truth topic."""
    root, folder, poses, labels = episode_folder
    kind = "mcap" if encoding in ("rgb8", "bgra8", "mono8") else "ros1"
    metres = encoding in ("bgr8", "bgra8")
    messages = camera_messages(
        folder, poses, kind, colour=encoding, odometry="tf", labels=labels,
        depth="32FC1" if metres else "16UC1", label_encoding="mono8" if metres else "mono16",
    )  # fmt: skip
    m = Messages(kind)
    messages += [("/gt", "geometry_msgs/msg/PoseStamped", s, m.pose_stamped(s, "map", T))
                 for s, T in zip(STAMPS, poses, strict=True)]  # fmt: skip
    bag = write_bag(tmp_path / "rec", kind, messages)
    labelled = tmp_path / "folder"
    shutil.copytree(folder, labelled, ignore=shutil.ignore_patterns("embeddings"))
    (labelled / "labels").mkdir()
    for t in range(FRAMES):
        Image.fromarray(labels[t]).save(labelled / "labels" / f"{t}.png")
    classes = ClassEmbeddings.onehot(CLASS_IDS)
    recording = read_bag_camera_sequence(
        bag, label_topic="/segmentation", classes=classes, gt_topic="/gt", patch_shape=(3, 4)
    )
    reference = read_camera_sequence(
        labelled, labels_dir=labelled / "labels", classes=classes, patch_shape=(3, 4)
    )
    if encoding == "mono8":  # grey colour: compare the colour with the folder's made grey
        grey = np.asarray(reference.sequence.rgb)[..., :1]
        np.testing.assert_allclose(np.asarray(recording.sequence.rgb), np.repeat(grey, 3, -1),
                                   atol=1 / 255)  # fmt: skip
    _assert_same_query(recording, reference, rgb_exact=encoding != "mono8",
                       depth_atol=1e-6 if metres else 0.0)  # fmt: skip
    np.testing.assert_allclose(recording.poses_gt, reference.poses_gt, atol=1e-9)


def test_open_camera_recording_reads_bags(episode_folder, tmp_path):
    """The one opener dispatches on a bag (topics named as keywords; embeddings/ beside a .bag)
    and reads frames lazily: a damaged JPEG after ``max_frames`` is never decoded."""
    root, folder, poses, _ = episode_folder
    messages = camera_messages(folder, poses, "ros1")
    topic, msgtype, stamp, _ = messages[
        -1 - [m[0] for m in messages[::-1]].index(COLOR + "/compressed")
    ]
    messages = [m for m in messages if not (m[0] == topic and m[2] == stamp)]
    messages.append(
        (topic, msgtype, stamp, Messages("ros1").compressed(stamp, CAM_FRAME, b"\xff\xd8junk"))
    )
    bag = write_bag(tmp_path / "rec", "ros1", messages)
    _embeddings_by_stamp(folder, tmp_path / "embeddings")
    opened = open_camera_recording(bag, image_topic=COLOR + "/compressed", max_frames=3)
    assert opened.frame_ids == (0, 1, 2) and opened.poses_gt is None
    with pytest.raises(
        ValueError,
        match=r"rec\.bag: /camera/color/image_raw/compressed \(message 3\): not a readable image",
    ):
        open_camera_recording(bag)


def _replace(messages, topic, index, **fields):
    """The messages with the ``index``-th message of ``topic`` changed (dataclass fields)."""
    at = [i for i, m in enumerate(messages) if m[0] == topic][index]
    out = list(messages)
    out[at] = (*out[at][:3], dataclasses.replace(out[at][3], **fields))
    return out


def _refused(tmp_path, kind, messages, *topics, **kwargs) -> str:
    """The one-line ValueError of opening the bag of ``messages``, which names it and
    ``topics``."""
    bag = write_bag(tmp_path / f"bad{len(list(tmp_path.iterdir()))}", kind, messages)
    with pytest.raises(ValueError) as info:
        read_bag_camera_sequence(bag, embeddings_dir=tmp_path / "e", **kwargs)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(bag)), message
    assert all(topic in message for topic in topics), message
    return message


def test_bad_bags_are_one_line_naming_the_bag_and_topic(episode_folder, tmp_path):
    root, folder, poses, _ = episode_folder
    _embeddings_by_stamp(folder, tmp_path / "e")
    good = camera_messages(folder, poses, "mcap")
    compressed = COLOR + "/compressed"
    message = _refused(tmp_path, "mcap", [m for m in good if m[0] != compressed])
    assert "no sensor_msgs/Image or CompressedImage colour topic (topics: " in message
    ros1 = camera_messages(folder, poses, "ros1")
    twice = ros1 + [("/camera2/image/compressed", *m[1:]) for m in ros1 if m[0] == compressed]
    message = _refused(tmp_path, "ros1", twice, compressed, "/camera2/image/compressed")
    assert "2 colour image topics" in message and "image_topic=" in message
    raw = camera_messages(folder, poses, "sqlite3", colour="rgb8")
    message = _refused(tmp_path, "sqlite3", _replace(raw, COLOR, 0, encoding="yuv422"), COLOR)
    assert "colour encoding 'yuv422' is not one of rgb8, bgr8" in message
    message = _refused(tmp_path, "mcap", _replace(good, DEPTH, 0, encoding="8UC1"), DEPTH,
                       depth_topic=DEPTH)  # fmt: skip
    assert "depth encoding '8UC1'" in message and "16UC1 millimetres or 32FC1 metres" in message
    packed = camera_messages(folder, poses, "mcap", depth="16UC1 compressedDepth")
    rvl = _replace(packed, DEPTH + "/compressedDepth", 0, format="16UC1; compressedDepth rvl")
    message = _refused(tmp_path, "mcap", rvl, DEPTH + "/compressedDepth")
    assert "compressed depth '16UC1; compressedDepth rvl' is not read" in message
    cut = _replace(packed, DEPTH + "/compressedDepth", 1, data=np.zeros(8, np.uint8))
    message = _refused(tmp_path, "mcap", cut, DEPTH + "/compressedDepth")
    assert "8 bytes, no compressedDepth image" in message
    later = Messages("ros1").header(STAMPS[0] - 1, CAM_FRAME)  # frame 2 stamped before frame 1
    message = _refused(tmp_path, "ros1", _replace(ros1, compressed, 2, header=later), compressed)
    assert "message 2's stamp" in message and "is not after message 1's" in message
    late = [m for m in good if not (m[0] == "/odom" and m[2] < STAMPS[1])]
    message = _refused(tmp_path, "mcap", late, "/odom")
    assert "covers" in message and "frame 0 at 1700000000.000000123 s is outside it" in message
    shifted = [(t, k, s + (10**9 if t == DEPTH else 0), msg) for t, k, s, msg in good]
    shifted = [(t, k, s, dataclasses.replace(msg, header=Messages("mcap").header(s, CAM_FRAME)))
               if t == DEPTH else (t, k, s, msg) for t, k, s, msg in shifted]  # fmt: skip
    message = _refused(tmp_path, "mcap", shifted, DEPTH)
    assert "has no message within 0.02 s of frame 0" in message
    two_depths = good + [("/depth2", *m[1:]) for m in good if m[0] == DEPTH]
    message = _refused(tmp_path, "mcap", two_depths, DEPTH, "/depth2")
    assert "2 depth image topics" in message and "depth_topic=" in message
    bag = write_bag(tmp_path / "two_depths", "mcap", two_depths)
    without = read_bag_camera_sequence(bag, embeddings_dir=tmp_path / "e", use_depth=False)
    assert without.sequence.depth is None
    no_odometry = [m for m in good if m[0] != "/odom"]
    message = _refused(tmp_path, "mcap", no_odometry, COLOR)
    assert "no poses for the ego-motion" in message
    message = _refused(tmp_path, "mcap", good, "/odom", odometry_topic="/odom2")
    assert "odometry_topic='/odom2' is not a nav_msgs/Odometry or /tf topic" in message


@pytest.mark.parametrize("kind", KINDS)
def test_a_truncated_bag_is_one_line_naming_it(episode_folder, kind, tmp_path):
    root, folder, poses, _ = episode_folder
    bag = write_bag(tmp_path / "rec", kind, camera_messages(folder, poses, kind))
    stored = bag if bag.is_file() else next(p for p in bag.iterdir() if p.suffix != ".yaml")
    stored.write_bytes(stored.read_bytes()[: stored.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"^[^\n]*: not a readable bag \(") as info:
        read_bag_camera_sequence(bag)
    assert str(info.value).startswith(str(bag))


def test_depth_of_its_own_size_with_its_camera_info(episode_folder, tmp_path):
    """Depth at half the colour size with a CameraInfo beside it lands on the colour pixels as a
    folder's depth with its intrinsic_depth.txt does; without that CameraInfo, one line."""
    root, folder, poses, _ = episode_folder
    half = tmp_path / "half"
    shutil.copytree(folder, half)
    K = np.loadtxt(folder / "intrinsic" / "intrinsic_color.txt")
    K_depth = K.copy()
    K_depth[[0, 1], [0, 1]] /= 2
    K_depth[[0, 1], 2] = (K[[0, 1], 2] + 0.5) / 2 - 0.5
    np.savetxt(half / "intrinsic" / "intrinsic_depth.txt", K_depth)  # %.18e: exact
    m = Messages("sqlite3")
    messages = [msg for msg in camera_messages(folder, poses, "sqlite3") if msg[0] != DEPTH]
    for t, stamp in enumerate(STAMPS):
        mm = np.asarray(Image.open(folder / "depth" / f"{t}.png")).astype(np.uint16)[::2, ::2]
        Image.fromarray(mm).save(half / "depth" / f"{t}.png")
        messages.append((DEPTH, "sensor_msgs/msg/Image", stamp, m.image(stamp, CAM_FRAME, mm,
                                                                         "16UC1")))  # fmt: skip
    info = ("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", STAMPS[0],
            m.camera_info(STAMPS[0], CAM_FRAME, K_depth, (32, 24)))  # fmt: skip
    bag = write_bag(tmp_path / "rec", "sqlite3", [*messages, info])
    embeddings = _embeddings_by_stamp(folder, tmp_path / "e")
    recording = read_bag_camera_sequence(bag, embeddings_dir=embeddings)
    _assert_same_query(recording, read_camera_sequence(half))
    assert np.count_nonzero(recording.sequence.depth) > 0.5 * recording.sequence.depth.size
    message = _refused(tmp_path, "sqlite3", messages, DEPTH)
    assert "is 32x24, /camera/color/image_raw/compressed 64x48" in message
    assert "depth_info_topic=" in message


def test_the_opener_reads_label_topics_through_the_maps_classes(episode_folder, tmp_path):
    """``open_camera_recording(map_file=, label_topic=)`` is the bag reader given the map's class
    embeddings; folder options for a bag and bag options for a folder are refused."""
    root, folder, poses, labels = episode_folder
    classes = ClassEmbeddings.onehot(CLASS_IDS)
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    save_scene(SceneGraph.from_meshes([box], [1], np.eye(3)[:1]), tmp_path / "map.npz", classes)
    bag = write_bag(tmp_path / "rec", "mcap", camera_messages(folder, poses, "mcap", labels=labels))
    opened = open_camera_recording(
        bag, map_file=tmp_path / "map.npz", label_topic="/segmentation", patch_shape=(3, 4)
    )
    direct = read_bag_camera_sequence(
        bag, label_topic="/segmentation", classes=classes, patch_shape=(3, 4)
    )
    np.testing.assert_array_equal(
        opened.sequence.patch_embeddings, direct.sequence.patch_embeddings
    )
    with pytest.raises(ValueError, match="label images come from label_topic, not labels_dir"):
        open_camera_recording(bag, labels_dir=tmp_path)
    with pytest.raises(ValueError, match=r"export: image_topic, gt apply to ROS bags only"):
        open_camera_recording(folder, image_topic="/x", gt=tmp_path / "gt.tum")


def test_localize_camera_on_a_bag(episode_folder, tmp_path, capsys):
    """``jaxloc localize-camera`` on a bag (``--format rosbag``, its topics and a TUM ground truth
    named on the command line): every frame localized and judged, the run written with
    ``--rerun`` as a recording Rerun's reader loads; bag options for a folder are one line."""
    root, folder, poses, _ = episode_folder
    bag = write_bag(tmp_path / "rec", "mcap", camera_messages(folder, poses, "mcap"))
    write_tum(tmp_path / "gt.tum", poses, np.asarray(STAMPS, np.int64))
    options = ["--embeddings", _embeddings_by_stamp(folder, tmp_path / "e"), "--width", "64",
               "--particles", "64", "--strides", "6", "--no-progress", "--json"]  # fmt: skip
    argv = ["localize-camera", root / "map.npz", bag, "--format", "rosbag", "--image-topic",
            COLOR + "/compressed", "--depth-topic", DEPTH, "--odometry-topic", "/odom", "--gt",
            tmp_path / "gt.tum", "--rerun", tmp_path / "run.rrd", *options]  # fmt: skip
    assert main([str(a) for a in argv]) == 0, capsys.readouterr().err
    report = json.loads(capsys.readouterr().out)
    assert report["format"] == "rosbag" and report["frames"] == list(range(FRAMES))
    assert len(report["position_error_m"]) == FRAMES
    assert report["rerun"] == str(tmp_path / "run.rrd")
    rerun_chunk = pytest.importorskip("rerun.chunk")
    chunks = rerun_chunk.RrdReader(tmp_path / "run.rrd").stream().to_chunks()
    assert {"/world/camera/image/rgb", "/world/trajectory/gt"} <= {c.entity_path for c in chunks}
    argv = ["localize-camera", root / "map.npz", folder, "--image-topic", "/x", *options]
    assert main([str(a) for a in argv]) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and error.endswith("export: image_topic apply to ROS bags only"), error
