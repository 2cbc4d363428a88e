"""Sequential scene retrieval (jaxloc.sg2loc.retrieval) against a loop-by-loop numpy reference.

Tiny galleries (a few scenes of a few objects in d = 8) keep every test to a fraction of a
second once compiled; the compiled shapes are shared between tests.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from _compilations import compilations

from jaxloc.scene import SceneGraph
from jaxloc.sg2loc import retrieval
from jaxloc.sg2loc.retrieval import Gallery, recall_at_k, retrieve, true_rank

DIM = 8
OBJECTS = (2, 5, 4)  # objects per scene


def reference_scores(patches: np.ndarray, scenes: list[np.ndarray]) -> np.ndarray:
    """(T, S) float64 frame scores by explicit loops: mean over patches with a non-zero norm of
    the best cosine with any object of the scene (0 for a frame without such patches)."""
    frames = patches.reshape(patches.shape[0], -1, patches.shape[-1]).astype(np.float64)
    out = np.zeros((len(frames), len(scenes)))
    for t, frame in enumerate(frames):
        for s, objects in enumerate(scenes):
            best = []
            for patch in frame:
                norm = np.linalg.norm(patch)
                if norm < retrieval.MIN_PATCH_NORM:
                    continue
                cosines = [float(patch @ obj) / (norm * np.linalg.norm(obj)) for obj in objects]
                best.append(max(cosines))
            out[t, s] = np.mean(best) if best else 0.0
    return out


def random_scenes(rng: np.random.Generator) -> list[np.ndarray]:
    return [rng.normal(size=(n, DIM)) * rng.uniform(0.5, 2.0) for n in OBJECTS]


def random_patches(rng: np.random.Generator, frames: int = 3) -> np.ndarray:
    patches = rng.normal(size=(frames, 2, 3, DIM)) * rng.uniform(0.1, 3.0, (frames, 2, 3, 1))
    patches[0, 1, 2] = 0.0  # a missing patch
    return patches.astype(np.float32)


def test_scores_match_numpy_reference():
    rng = np.random.default_rng(0)
    scenes = random_scenes(rng)
    patches = random_patches(rng)
    patches[2] = 0.0  # a frame without any patch direction contributes 0
    result = retrieve(patches, Gallery.from_embeddings(scenes))
    expected = reference_scores(patches, scenes)
    np.testing.assert_allclose(result.frame_scores, expected, atol=1e-5)
    np.testing.assert_allclose(result.scores, expected.sum(axis=0), atol=1e-5)
    np.testing.assert_array_equal(result.ranking, np.argsort(-expected.sum(axis=0), kind="stable"))
    assert bool(result.valid)
    assert np.all(np.asarray(result.frame_scores)[2] == 0.0)


def test_padding_objects_scenes_patches_and_frames_changes_nothing():
    rng = np.random.default_rng(1)
    scenes = random_scenes(rng)
    patches = random_patches(rng)
    plain = retrieve(patches, Gallery.from_embeddings(scenes))
    padded_gallery = Gallery.from_embeddings(scenes, object_capacity=9, scene_capacity=6)
    padded_patches = np.zeros((5, 3, 3, DIM), np.float32)  # 2 more frames, 3 more patches
    padded_patches[:3, :2, :] = patches
    padded = retrieve(padded_patches, padded_gallery)
    num = len(scenes)
    np.testing.assert_allclose(padded.scores[:num], plain.scores, atol=1e-6)
    assert np.all(np.isneginf(np.asarray(padded.scores)[num:]))
    np.testing.assert_array_equal(padded.ranking[:num], plain.ranking)
    np.testing.assert_array_equal(np.sort(np.asarray(padded.ranking)[num:]), np.arange(num, 6))
    np.testing.assert_allclose(padded.frame_scores[3:, :num], 0.0)
    assert np.all(np.isfinite(np.asarray(padded.scores)[:num]))


def test_jit_equals_eager_and_no_retrace():
    rng = np.random.default_rng(2)
    gallery = Gallery.from_embeddings(random_scenes(rng))
    patches = random_patches(rng)
    with jax.disable_jit():
        eager = retrieve(patches, gallery)
    jitted = jax.jit(retrieve)(jnp.asarray(patches), gallery)
    for a, b in zip(eager, jitted, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)

    retrieve(patches, gallery)  # compiles the (3, 6, 8) x (3, 5, 8) shapes if not yet done
    with compilations() as compiled:
        for seed in range(3):  # new queries and new galleries of the same shapes: no new program
            other = np.random.default_rng(100 + seed)
            new_gallery = Gallery.from_embeddings(random_scenes(other), object_capacity=5)
            retrieve(random_patches(other), new_gallery).scores.block_until_ready()
    assert not [c for c in compiled if "_retrieve" in c], compiled


def test_from_scene_graphs_uses_the_valid_objects():
    rng = np.random.default_rng(3)
    boxes = [
        trimesh.creation.box(extents=(1, 1, 1)).apply_translation((2.0 * i, 0, 0)) for i in range(3)
    ]
    emb = rng.normal(size=(3, DIM))
    scene = SceneGraph.from_meshes(boxes, [0, 1, 2], emb, capacity=None)
    padded = SceneGraph.from_meshes(
        boxes, [0, 1, 2], emb, capacity=scene.capacity._replace(objects=7)
    )
    gallery = Gallery.from_scene_graphs([scene, padded])
    np.testing.assert_array_equal(gallery.num_objects(), [3, 3])
    np.testing.assert_allclose(gallery.storage_mb(), [3 * DIM * 4 / 1e6] * 2)
    patches = random_patches(rng)
    result = retrieve(patches, gallery)
    expected = reference_scores(patches, [emb, emb]).sum(axis=0)
    np.testing.assert_allclose(result.scores, expected, atol=1e-5)


def test_true_rank_and_recall_match_argsort():
    rng = np.random.default_rng(4)
    scores = rng.integers(0, 4, size=(50, 7)).astype(np.float32)  # many ties
    truth = rng.integers(0, 7, size=50)
    ranks = np.asarray(true_rank(scores, truth))
    order = np.argsort(-scores, axis=1, kind="stable")
    expected = np.array([int(np.flatnonzero(o == t)[0]) for o, t in zip(order, truth, strict=True)])
    np.testing.assert_array_equal(ranks, expected)
    recalls = recall_at_k(ranks, (1, 3, 5))
    for k, value in recalls.items():
        assert value == pytest.approx(np.mean(expected < k))
    assert recalls[1] <= recalls[3] <= recalls[5]


def test_bad_inputs_raise_clear_errors():
    rng = np.random.default_rng(5)
    scenes = random_scenes(rng)
    gallery = Gallery.from_embeddings(scenes)
    with pytest.raises(ValueError, match="patch_embeddings have 5 dims but the gallery"):
        retrieve(np.ones((2, 3, 5), np.float32), gallery)
    with pytest.raises(ValueError, match=r"patch_embeddings must have shape \(T, \.\.\., d\)"):
        retrieve(np.ones((3, DIM), np.float32), gallery)
    nan_patches = random_patches(rng)
    nan_patches[1, 0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="patch_embeddings contains 1 NaN/inf"):
        retrieve(nan_patches, gallery)
    with pytest.raises(ValueError, match=r"embeddings\[1\] contains NaN"):
        Gallery.from_embeddings([scenes[0], np.full((2, DIM), np.nan)])
    with pytest.raises(ValueError, match="zero vectors"):
        Gallery.from_embeddings([np.zeros((1, DIM))])
    with pytest.raises(ValueError, match="one embedding dimension"):
        Gallery.from_embeddings([np.ones((2, DIM)), np.ones((2, DIM + 1))])
    with pytest.raises(ValueError, match="object_capacity 3 < 5"):
        Gallery.from_embeddings(scenes, object_capacity=3)
    with pytest.raises(ValueError, match="at least one scene"):
        Gallery.from_embeddings([])
    with pytest.raises(TypeError, match="gallery must be"):
        retrieve(random_patches(rng), scenes)


def test_nan_under_jit_is_a_flag_not_a_nan_score():
    rng = np.random.default_rng(6)
    gallery = Gallery.from_embeddings(random_scenes(rng))
    patches = random_patches(rng)
    clean = patches.copy()
    clean[1, 0, 0] = 0.0  # the NaN patch below is left out exactly like a missing patch
    patches[1, 0, 0, 3] = np.nan
    result = jax.jit(retrieve)(jnp.asarray(patches), gallery)
    assert not bool(result.valid)
    assert np.all(np.isfinite(np.asarray(result.scores)))
    np.testing.assert_allclose(result.scores, retrieve(clean, gallery).scores, atol=1e-6)
