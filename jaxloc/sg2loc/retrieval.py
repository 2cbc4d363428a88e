"""Sequential scene retrieval: which scene graph of a database does a query sequence show?

SceneGraphLoc (Miao et al., 2024) scores a candidate scene graph ``G`` for one image ``I_t`` as the
mean over the image's patches of the best cosine similarity between the patch embedding and any
of the scene's object embeddings; SG2Loc (section 4) sums these frame scores over a sequence::

    score_t(G) = 1/|Q_t| sum_{q in Q_t} max_{v in G} cos(e_q, e_v)
    score(G)   = sum_{t=1..T} score_t(G)

and ranks the candidates by ``score``. Here the candidates are stacked into a :class:`Gallery`
(S scenes padded to O object slots) so one compiled function scores every candidate at once;
maps with the same ``(S, O, d)`` and queries with the same ``(T, P, d)`` share it (no retrace).

Missing patches: a patch embedding with norm below :data:`MIN_PATCH_NORM` (e.g. an all-zero
vector marking a masked or padded patch) has no direction; it is left out of its frame's mean.
A frame without any such direction contributes 0 to every candidate, so zero-padding a query
with extra frames or patches leaves its scores unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.scene import SceneGraph

#: Patch embeddings with a smaller Euclidean norm count as missing (left out of the frame mean).
MIN_PATCH_NORM = 1e-12
#: Bytes per stored embedding entry (float32): the storage the retrieval database needs.
BYTES_PER_VALUE = 4


class Gallery(eqx.Module):
    """Candidate scene graphs' object embeddings, stacked and padded (S scenes, O object slots).

    Attributes:
        embeddings: (S, O, d) float32 unit-norm object embeddings, zeros in padding slots.
        object_valid: (S, O) bool, real objects.
        scene_valid: (S,) bool, real scenes (a padding scene has no valid object and scores
            ``-inf``, so it ranks last).

    Build one with :meth:`from_scene_graphs` or :meth:`from_embeddings`.
    """

    embeddings: Array
    object_valid: Array
    scene_valid: Array

    def __check_init__(self):
        shape = self.embeddings.shape
        if len(shape) != 3:
            raise ValueError(f"embeddings must have shape (S, O, d), got {shape}")
        if self.object_valid.shape != shape[:2]:
            raise ValueError(
                f"object_valid must have shape (S, O) = {shape[:2]}, got {self.object_valid.shape}"
            )
        if self.scene_valid.shape != shape[:1]:
            raise ValueError(
                f"scene_valid must have shape (S,) = {shape[:1]}, got {self.scene_valid.shape}"
            )

    @property
    def num_slots(self) -> int:
        """S, the number of scene slots (real and padding)."""
        return self.embeddings.shape[0]

    @property
    def object_capacity(self) -> int:
        """O, the number of object slots per scene."""
        return self.embeddings.shape[1]

    @property
    def embedding_dim(self) -> int:
        """d, the embedding dimension."""
        return self.embeddings.shape[2]

    def num_objects(self) -> np.ndarray:
        """(S,) int: real objects per scene slot (host values)."""
        return np.sum(np.asarray(self.object_valid), axis=1)

    def storage_mb(self) -> np.ndarray:
        """(S,) float: MB (10^6 bytes) each scene's embeddings take as float32, padding excluded.

        This is the retrieval database's storage, the quantity of SG2Loc's Table 5; the full map
        used for localization (meshes included) is :meth:`jaxloc.SceneGraph.storage_mb`.
        """
        return self.num_objects() * self.embedding_dim * BYTES_PER_VALUE / 1e6

    @staticmethod
    def from_embeddings(
        embeddings: Sequence,
        *,
        object_capacity: int | None = None,
        scene_capacity: int | None = None,
    ) -> Gallery:
        """Stack per-scene object embeddings into a padded gallery.

        Args:
            embeddings: S arrays of shape (n_s, d), n_s >= 1 objects each, one common d; any
                non-zero norm (they are normalised).
            object_capacity: O, object slots per scene (default: the largest n_s). A fixed value
                lets galleries of different scenes share compiled code.
            scene_capacity: scene slots (default S); extra slots are padding scenes.

        Raises:
            ValueError: no scenes, bad shapes, differing d, NaN/inf or zero vectors, or a
                capacity smaller than the content.
        """
        arrays = []
        for s, emb in enumerate(embeddings):
            emb = np.asarray(emb)
            if emb.ndim != 2 or emb.shape[0] < 1 or emb.shape[1] < 1:
                raise ValueError(
                    f"embeddings[{s}] must have shape (n, d) with n, d >= 1, got {emb.shape}"
                )
            if not (np.issubdtype(emb.dtype, np.floating) or np.issubdtype(emb.dtype, np.integer)):
                raise TypeError(f"embeddings[{s}] must be real numbers, got dtype {emb.dtype}")
            emb = emb.astype(np.float64)
            if not np.all(np.isfinite(emb)):
                raise ValueError(f"embeddings[{s}] contains NaN or inf")
            norms = np.linalg.norm(emb, axis=1)
            if np.any(norms == 0):
                rows = np.flatnonzero(norms == 0).tolist()
                raise ValueError(f"embeddings[{s}] has zero vectors at rows {rows}")
            arrays.append(emb / norms[:, None])
        if not arrays:
            raise ValueError("a gallery needs at least one scene")
        dims = {a.shape[1] for a in arrays}
        if len(dims) != 1:
            raise ValueError(f"all scenes must share one embedding dimension, got {sorted(dims)}")
        (dim,) = dims
        most = max(a.shape[0] for a in arrays)
        object_capacity = most if object_capacity is None else object_capacity
        scene_capacity = len(arrays) if scene_capacity is None else scene_capacity
        if object_capacity < most:
            raise ValueError(f"object_capacity {object_capacity} < {most} objects of a scene")
        if scene_capacity < len(arrays):
            raise ValueError(f"scene_capacity {scene_capacity} < {len(arrays)} scenes")
        stacked = np.zeros((scene_capacity, object_capacity, dim), np.float32)
        valid = np.zeros((scene_capacity, object_capacity), bool)
        for s, emb in enumerate(arrays):
            stacked[s, : emb.shape[0]] = emb
            valid[s, : emb.shape[0]] = True
        return Gallery(jnp.asarray(stacked), jnp.asarray(valid), jnp.asarray(valid.any(axis=1)))

    @staticmethod
    def from_scene_graphs(
        scenes: Sequence[SceneGraph],
        *,
        object_capacity: int | None = None,
        scene_capacity: int | None = None,
    ) -> Gallery:
        """A gallery of the valid objects' embeddings of each :class:`jaxloc.SceneGraph`.

        Capacities as in :meth:`from_embeddings`.
        """
        embeddings = []
        for s, scene in enumerate(scenes):
            if not isinstance(scene, SceneGraph):
                raise TypeError(f"scenes[{s}] must be a jaxloc.SceneGraph, got {type(scene)}")
            valid = np.asarray(scene.object_valid)
            embeddings.append(np.asarray(scene.embeddings)[valid])
        return Gallery.from_embeddings(
            embeddings, object_capacity=object_capacity, scene_capacity=scene_capacity
        )


class Retrieval(NamedTuple):
    """Output of :func:`retrieve` (S scene slots, T frames).

    Attributes:
        scores: (S,) float32 sequence score of every candidate, ``-inf`` for padding slots.
        ranking: (S,) int32 scene indices from best to worst (ties: lower index first).
        frame_scores: (T, S) float32 per-frame scores (``-inf`` for padding slots).
        valid: () bool, the query had finite embeddings and at least one patch with a direction.
    """

    scores: Array
    ranking: Array
    frame_scores: Array
    valid: Array


def _frame_scene_score(
    patch_units: Array, patch_valid: Array, objects: Array, object_valid: Array
) -> Array:
    """Mean over valid patches of the best cosine with a valid object (one frame, one scene).

    Args:
        patch_units: (P, d) unit patch embeddings (zeros where not valid).
        patch_valid: (P,) bool.
        objects: (O, d) unit object embeddings; object_valid: (O,) bool.

    Returns:
        () float32, 0 for a frame without valid patches or a scene without valid objects.
    """
    cosine = jnp.matmul(patch_units, objects.T, precision="highest")  # (P, O)
    best = jnp.max(jnp.where(object_valid[None, :], cosine, -jnp.inf), axis=1)
    best = jnp.where(patch_valid & jnp.any(object_valid), best, 0.0)
    return jnp.sum(best) / jnp.maximum(jnp.sum(patch_valid), 1)


def _unit_patches(patches: Array) -> tuple[Array, Array, Array]:
    """Normalised (T, P, d) patches, their (T, P) validity and whether all values were finite."""
    finite = jnp.all(jnp.isfinite(patches), axis=-1)
    safe = jnp.where(finite[..., None], patches, 0.0)
    norm = jnp.linalg.norm(safe, axis=-1)
    valid = finite & (norm >= MIN_PATCH_NORM)
    units = jnp.where(valid[..., None], safe / jnp.where(valid, norm, 1.0)[..., None], 0.0)
    return units, valid, jnp.all(finite)


def _frame_scores(patches: Array, gallery: Gallery) -> tuple[Array, Array]:
    units, valid, finite = _unit_patches(patches)
    per_scene = jax.vmap(_frame_scene_score, in_axes=(None, None, 0, 0))
    scores = jax.lax.map(
        lambda frame: per_scene(frame[0], frame[1], gallery.embeddings, gallery.object_valid),
        (units, valid),
    )  # (T, S), one frame at a time to bound memory to (P, S, O)
    scores = jnp.where(gallery.scene_valid[None, :], scores, -jnp.inf)
    return scores, finite & jnp.any(valid)


def _flatten_patches(patch_embeddings, gallery: Gallery) -> Array:
    """(T, ..., d) -> (T, P, d) float32, with shape checks (and value checks when concrete)."""
    if not isinstance(gallery, Gallery):
        raise TypeError(f"gallery must be a jaxloc.sg2loc.retrieval.Gallery, got {type(gallery)}")
    shape = jnp.shape(patch_embeddings)
    if len(shape) < 3:
        raise ValueError(
            f"patch_embeddings must have shape (T, ..., d) (e.g. (T, rows, cols, d)), got {shape}"
        )
    if shape[-1] != gallery.embedding_dim:
        raise ValueError(
            f"patch_embeddings have {shape[-1]} dims but the gallery's objects have "
            f"{gallery.embedding_dim}"
        )
    if not isinstance(patch_embeddings, jax.core.Tracer):
        values = np.asarray(patch_embeddings)
        if not np.all(np.isfinite(values)):
            bad = int(values.size - np.count_nonzero(np.isfinite(values)))
            raise ValueError(f"patch_embeddings contains {bad} NaN/inf values")
    patches = jnp.asarray(patch_embeddings, jnp.float32)
    return patches.reshape(shape[0], -1, shape[-1])


@eqx.filter_jit
def _retrieve(patches: Array, gallery: Gallery) -> Retrieval:
    frame_scores, valid = _frame_scores(patches, gallery)
    scores = jnp.sum(frame_scores, axis=0)
    ranking = jnp.argsort(-scores, stable=True).astype(jnp.int32)
    return Retrieval(scores, ranking, frame_scores, valid)


def retrieve(patch_embeddings: Array, gallery: Gallery) -> Retrieval:
    """Score and rank every candidate scene of ``gallery`` for one query sequence (jitted).

    Args:
        patch_embeddings: (T, ..., d) patch embeddings of T frames (e.g. a
            :class:`jaxloc.FrameSequence`'s (T, rows, cols, d)); any norm, compared by cosine;
            patches with norm < :data:`MIN_PATCH_NORM` are missing (see the module docstring).
        gallery: the candidates.

    Returns:
        :class:`Retrieval` (scores, ranking, per-frame scores, valid flag).

    Raises:
        ValueError: patch and gallery dimensions differ, or (for concrete inputs) the
            embeddings contain NaN/inf. Inside a caller's ``jit`` non-finite patches are left
            out of the scores and ``valid`` is False instead.
    """
    return _retrieve(_flatten_patches(patch_embeddings, gallery), gallery)


def true_rank(scores: Array, true_index: Array) -> Array:
    """Position (0 = best) of the true scene in the ranking, ties broken by scene index.

    Args:
        scores: (..., S) candidate scores; true_index: (...,) int index of the true scene.

    Returns:
        (...,) int32, consistent with :attr:`Retrieval.ranking` (``ranking[rank] == true``).
    """
    scores = jnp.asarray(scores)
    true_index = jnp.asarray(true_index, jnp.int32)
    true_score = jnp.take_along_axis(scores, true_index[..., None], axis=-1)
    index = jnp.arange(scores.shape[-1])
    better = (scores > true_score) | ((scores == true_score) & (index < true_index[..., None]))
    return jnp.sum(better, axis=-1).astype(jnp.int32)


def recall_at_k(ranks, ks: Sequence[int] = (1, 3, 5)) -> dict[int, float]:
    """Fraction of queries whose true scene is among the top k, for each k (host floats).

    Args:
        ranks: (Q,) 0-based ranks from :func:`true_rank`.
        ks: the cut-offs (positive ints).
    """
    ranks = np.asarray(ranks)
    if ranks.size == 0:
        raise ValueError("recall_at_k needs at least one rank")
    if any(int(k) < 1 for k in ks):
        raise ValueError(f"ks must be positive, got {tuple(ks)}")
    return {int(k): float(np.mean(ranks < k)) for k in ks}
