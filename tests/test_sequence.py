"""Validation of :class:`jaxloc.FrameSequence`: bad input fails at the boundary, clearly.

Every check builds a small valid sequence (T = 3 frames, a 32x18 camera, a 3x4 patch grid,
8-d embeddings), breaks one argument, and matches the error type and message. Host-side only:
nothing here compiles or raycasts.
"""

from __future__ import annotations

import numpy as np
import pytest

from jaxloc import Camera, FrameSequence

T, ROWS, COLS, DIM = 3, 3, 4, 8
CAMERA = Camera.from_fov(32, 18, 60.0)
H, W = CAMERA.height, CAMERA.width


def valid_arrays(seed: int = 0) -> dict[str, np.ndarray]:
    """Keyword arguments of a valid sequence (float64, to check the float32 conversion)."""
    rng = np.random.default_rng(seed)
    return {
        "patch_embeddings": rng.normal(size=(T, ROWS, COLS, DIM)),
        "ego_motion": rng.normal(scale=0.1, size=(T - 1, 4)),
        "depth": rng.uniform(0.0, 5.0, size=(T, H, W)),
        "rgb": rng.uniform(0.0, 1.0, size=(T, H, W, 3)),
        "tilt": rng.normal(scale=0.05, size=(T, 2)),
    }


def make(**overrides) -> FrameSequence:
    """A sequence from :func:`valid_arrays` with some arguments replaced."""
    kwargs = valid_arrays()
    kwargs.update(overrides)
    return FrameSequence(CAMERA, **kwargs)


def test_valid_sequence_is_float32_and_keeps_values():
    arrays = valid_arrays()
    seq = FrameSequence(CAMERA, **arrays)
    assert seq.num_frames == T and seq.patch_shape == (ROWS, COLS)
    for name in ("patch_embeddings", "ego_motion", "depth", "rgb", "tilt"):
        value = getattr(seq, name)
        assert isinstance(value, np.ndarray) and value.dtype == np.float32, name
        np.testing.assert_allclose(value, arrays[name], rtol=1e-6, atol=1e-7, err_msg=name)


def test_optional_inputs_default_to_none_and_level():
    arrays = valid_arrays()
    seq = FrameSequence(CAMERA, arrays["patch_embeddings"], arrays["ego_motion"])
    assert seq.depth is None and seq.rgb is None
    assert seq.tilt.shape == (T, 2) and seq.tilt.dtype == np.float32
    assert not np.any(seq.tilt)


def test_single_frame_and_integer_inputs_are_accepted():
    emb = np.ones((1, ROWS, COLS, DIM), np.int64)
    seq = FrameSequence(CAMERA, emb, np.zeros((0, 4)), depth=np.zeros((1, H, W), np.uint16))
    assert seq.num_frames == 1 and seq.ego_motion.shape == (0, 4)
    assert seq.patch_embeddings.dtype == np.float32 and seq.depth.dtype == np.float32


def test_camera_must_be_a_camera():
    arrays = valid_arrays()
    with pytest.raises(TypeError, match="camera must be a jaxloc.Camera"):
        FrameSequence((32, 18), arrays["patch_embeddings"], arrays["ego_motion"])


@pytest.mark.parametrize(
    "shape", [(T, ROWS * COLS, DIM), (T, ROWS, COLS, DIM, 1), (DIM,)], ids=["3d", "5d", "1d"]
)
def test_embeddings_of_wrong_rank(shape):
    with pytest.raises(ValueError, match=r"patch_embeddings must have 4 dimensions, got shape"):
        make(patch_embeddings=np.ones(shape))


@pytest.mark.parametrize(
    "value",
    [
        np.full((T, ROWS, COLS, DIM), "a"),
        np.ones((T, ROWS, COLS, DIM), bool),
        np.ones((T, ROWS, COLS, DIM), np.complex64),
        np.full((T, ROWS, COLS, DIM), None, object),
    ],
    ids=["str", "bool", "complex", "object"],
)
def test_embeddings_of_wrong_dtype(value):
    with pytest.raises(TypeError, match="patch_embeddings must be a real numeric array, got dtype"):
        make(patch_embeddings=value)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_embeddings(bad):
    emb = valid_arrays()["patch_embeddings"]
    emb[1, 2, 3, 4] = bad
    emb[0, 0, 0, 0] = bad
    with pytest.raises(ValueError, match="patch_embeddings contains 2 NaN/inf values"):
        make(patch_embeddings=emb)


def test_a_zero_embedding_is_a_patch_without_evidence():
    """A zero vector (a patch whose label image holds no class of the map) is accepted; it
    predicts no object and adds nothing to either semantic score: the score equals that of the
    same view with the patch rendering nothing."""
    from jaxloc.sg2loc._scores import match_patches, semantic_score

    emb = valid_arrays()["patch_embeddings"]
    emb[2, 1, 0] = 0.0
    sequence = make(patch_embeddings=emb)
    objects = np.random.default_rng(1).normal(size=(5, DIM))
    patches = np.asarray(sequence.patch_embeddings[2]).reshape(-1, DIM)
    match = match_patches(patches, objects, np.ones(5, bool))
    zero = 1 * COLS + 0
    assert int(match.predicted[zero]) == -1
    rendered = np.asarray(match.predicted).copy()
    rendered[zero] = 3  # the zero patch sees object 3
    hidden = rendered.copy()
    hidden[zero] = -1
    for variant in ("gated", "soft"):
        assert float(semantic_score(match, rendered, variant)) == pytest.approx(
            float(semantic_score(match, hidden, variant))
        )


def test_no_frames():
    with pytest.raises(ValueError, match="at least one frame"):
        FrameSequence(CAMERA, np.ones((0, ROWS, COLS, DIM)), np.zeros((0, 4)))


@pytest.mark.parametrize("frames", [T, T - 2, 0], ids=["T", "T-2", "none"])
def test_ego_motion_of_wrong_length(frames):
    with pytest.raises(ValueError, match=r"ego_motion must have shape \(T-1, 4\) = \(2, 4\)"):
        make(ego_motion=np.zeros((frames, 4)))


def test_ego_motion_with_three_components_divisible_by_four():
    # (4, 3) has 12 elements, so it reshapes to (3, 4) before the shape check: still rejected.
    with pytest.raises(ValueError, match=r"ego_motion must have shape \(T-1, 4\)"):
        FrameSequence(CAMERA, np.ones((5, ROWS, COLS, DIM)), np.zeros((4, 3)))


def test_ego_motion_with_three_components():
    with pytest.raises(ValueError, match=r"ego_motion must have shape \(T-1, 4\)"):
        make(ego_motion=np.zeros((T - 1, 3)))


def test_ego_motion_with_nan():
    motion = valid_arrays()["ego_motion"]
    motion[1, 3] = np.nan
    with pytest.raises(ValueError, match="ego_motion contains 1 NaN/inf values"):
        make(ego_motion=motion)


@pytest.mark.parametrize(
    "shape", [(T, W, H), (T, H + 1, W), (T + 1, H, W)], ids=["transposed", "height", "frames"]
)
def test_depth_of_wrong_image_size(shape):
    with pytest.raises(ValueError, match=r"depth must have shape \(T, H, W\) = \(3, 18, 32\)"):
        make(depth=np.ones(shape))


def test_depth_of_wrong_rank():
    with pytest.raises(ValueError, match="depth must have 3 dimensions"):
        make(depth=np.ones((T, H, W, 1)))


def test_negative_depth():
    depth = valid_arrays()["depth"]
    depth[1, 5, 7] = -0.1
    with pytest.raises(ValueError, match=r"depth must be >= 0 \(0 marks an invalid pixel\)"):
        make(depth=depth)


def test_nan_depth():
    depth = valid_arrays()["depth"]
    depth[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="depth contains 1 NaN/inf values"):
        make(depth=depth)


def test_all_zero_depth_is_valid_input():
    seq = make(depth=np.zeros((T, H, W)))
    assert seq.depth is not None and not np.any(seq.depth)


@pytest.mark.parametrize("bad", [-0.01, 1.01, 255.0])
def test_rgb_out_of_range(bad):
    rgb = valid_arrays()["rgb"]
    rgb[2, 3, 4, 1] = bad
    with pytest.raises(ValueError, match=r"rgb values must lie in \[0, 1\]"):
        make(rgb=rgb)


def test_rgb_bounds_are_inclusive():
    rgb = valid_arrays()["rgb"]
    rgb[0, 0, 0] = 0.0
    rgb[1, 1, 1] = 1.0
    make(rgb=rgb)


@pytest.mark.parametrize(
    ("shape", "pattern"),
    [
        ((T, H, W), "rgb must have 4 dimensions"),
        ((T, H, W, 4), r"rgb must have shape \(T, H, W, 3\) = \(3, 18, 32, 3\)"),
        ((T, W, H, 3), r"rgb must have shape \(T, H, W, 3\)"),
    ],
    ids=["gray", "rgba", "transposed"],
)
def test_rgb_of_wrong_shape(shape, pattern):
    with pytest.raises(ValueError, match=pattern):
        make(rgb=np.full(shape, 0.5))


@pytest.mark.parametrize(
    ("shape", "pattern"),
    [
        ((T, 3), r"tilt must have shape \(T, 2\) = \(3, 2\), got \(3, 3\)"),
        ((T + 1, 2), r"tilt must have shape \(T, 2\) = \(3, 2\), got \(4, 2\)"),
        ((2,), "tilt must have 2 dimensions"),
    ],
    ids=["three-angles", "frames", "unbatched"],
)
def test_tilt_of_wrong_shape(shape, pattern):
    with pytest.raises(ValueError, match=pattern):
        make(tilt=np.zeros(shape))


def test_tilt_with_nan():
    tilt = valid_arrays()["tilt"]
    tilt[0, 1] = np.nan
    with pytest.raises(ValueError, match="tilt contains 1 NaN/inf values"):
        make(tilt=tilt)


def test_inputs_are_copied():
    """Mutating the caller's arrays afterwards does not change the sequence."""
    arrays = {k: v.astype(np.float32) for k, v in valid_arrays().items()}
    seq = FrameSequence(CAMERA, **arrays)
    before = {k: getattr(seq, k).copy() for k in arrays}
    for value in arrays.values():
        value[...] = 0.0
    for name, value in before.items():
        np.testing.assert_array_equal(getattr(seq, name), value, err_msg=name)


@pytest.mark.parametrize("depth, rgb", [(True, True), (False, True), (True, False)])
def test_zeros_has_the_shapes_and_dtypes_of_a_recording(depth, rgb):
    """``FrameSequence.zeros`` (the placeholder ``warm_up`` compiles from) matches a real
    sequence of the same sizes leaf for leaf: the same shapes, dtypes and missing images."""
    kwargs = valid_arrays()
    kwargs.update(depth=kwargs["depth"] if depth else None, rgb=kwargs["rgb"] if rgb else None)
    real = FrameSequence(CAMERA, **kwargs)
    zeros = FrameSequence.zeros(CAMERA, T, (ROWS, COLS), DIM, depth=depth, rgb=rgb)

    def layout(sequence):
        return [
            (a.shape, a.dtype)
            for a in (sequence.patch_embeddings, sequence.ego_motion, sequence.tilt)
        ] + [None if a is None else (a.shape, a.dtype) for a in (sequence.depth, sequence.rgb)]

    assert layout(zeros) == layout(real)
    assert not np.any(zeros.patch_embeddings) and not np.any(zeros.tilt)


def test_zeros_of_one_frame_has_no_motion():
    one = FrameSequence.zeros(CAMERA, 1, (ROWS, COLS), DIM)
    assert one.num_frames == 1 and one.ego_motion.shape == (0, 4)
