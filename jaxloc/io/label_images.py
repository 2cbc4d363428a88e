"""Query patch embeddings from per-frame label images, in a map's class-embedding space.

A label image holds one class id per pixel (0 = unknown), from ScanNet's ``label-filt/N.png``
(16-bit PNGs of raw ScanNet label ids, mapped to the map's classes with
``scannetv2-labels.combined.tsv``: ScanNet/ScanNet ``README.md``,
``BenchmarkScripts/2d_helpers/convert_scannet_label_image.py``) or from any segmentation network
(8- or 16-bit PNGs of class ids). Each patch of a ``rows x cols`` grid (the patches of
:func:`jaxloc.stride_grid`: equal rectangles of the image) gets the histogram of its pixels'
classes among the map's classes, and its embedding is the histogram-weighted sum of the class
embeddings (:class:`~jaxloc.io.scene_map.ClassEmbeddings`), unit-normalised: with a one-hot map a
patch of one class gets exactly that class's vector. A patch with no pixel of a map class gets a
zero vector, which adds nothing to the semantic score. The grid is laid over the label image at
its own resolution, so label images need the colour images' field of view, not their size.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from jaxloc.io.camera_frames import read_image
from jaxloc.io.scene_map import ClassEmbeddings


def read_label_image(path: str | os.PathLike) -> np.ndarray:
    """(H, W) int64 class ids of an 8- or 16-bit one-channel image (PNG).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: not a readable image, not one channel of 8 or 16 bits.
    """
    image = read_image(Path(path))
    if image.mode not in ("L", "P", "I;16", "I;16B", "I;16L", "I"):
        raise ValueError(
            f"{path}: expected an 8- or 16-bit one-channel label image, got {image.mode}"
        )
    labels = np.asarray(image).astype(np.int64)
    if labels.ndim != 2 or labels.min(initial=0) < 0:
        raise ValueError(f"{path}: expected one non-negative class id per pixel")
    return labels


def patch_class_histograms(
    labels: np.ndarray, rows: int, cols: int, class_ids: np.ndarray
) -> np.ndarray:
    """Pixel counts (rows, cols, K) of each class of ``class_ids`` (K,) in each patch of the
    ``rows x cols`` grid over ``labels`` (H, W) (pixel (v, u) lies in patch
    ``(floor((v + 0.5) rows / H), floor((u + 0.5) cols / W))``); other ids are not counted."""
    labels = np.asarray(labels)
    height, width = labels.shape
    row = np.minimum(((np.arange(height) + 0.5) * rows / height).astype(np.int64), rows - 1)
    col = np.minimum(((np.arange(width) + 0.5) * cols / width).astype(np.int64), cols - 1)
    class_ids = np.asarray(class_ids, np.int64)
    slot = np.searchsorted(class_ids, labels)
    known = (slot < class_ids.size) & (class_ids[np.minimum(slot, class_ids.size - 1)] == labels)
    cell = (row[:, None] * cols + col[None, :]) * class_ids.size + slot
    counts = np.bincount(cell[known], minlength=rows * cols * class_ids.size)
    return counts.reshape(rows, cols, class_ids.size).astype(np.float64)


def patch_embeddings_from_labels(
    label_images,
    rows: int,
    cols: int,
    classes: ClassEmbeddings,
    id_map: Mapping[int, int] | None = None,
) -> np.ndarray:
    """Patch embeddings (T, rows, cols, d) float32 of label images (T, H, W) (or one (H, W)).

    Args:
        label_images: integer class ids per pixel, 0 = unknown (never a class).
        rows: patch rows of the grid (the query's embeddings are (T, rows, cols, d)).
        cols: patch columns of the grid.
        classes: the map's class embeddings.
        id_map: optional raw id -> class id (e.g. ScanNet label ids -> NYU40); ids it lacks
            become unknown.

    Returns:
        Unit vectors, and zero vectors for patches without a pixel of a map class.

    Raises:
        ValueError: non-integer or negative labels, a grid of fewer than one patch per side.
    """
    classes.check()
    images = np.asarray(label_images)
    if images.ndim == 2:
        images = images[None]
    if images.ndim != 3 or not np.issubdtype(images.dtype, np.integer):
        raise ValueError(
            f"label_images must be integer (T, H, W), got {images.dtype} {images.shape}"
        )
    if images.size and images.min() < 0:
        raise ValueError("label_images must be >= 0 (0 = unknown)")
    if rows < 1 or cols < 1:
        raise ValueError(f"the patch grid needs rows, cols >= 1, got {rows} x {cols}")
    if id_map is not None:
        raw = np.unique(images)
        mapped = np.asarray([id_map.get(int(r), 0) for r in raw], np.int64)
        images = mapped[np.searchsorted(raw, images)]
    ids = np.asarray(classes.class_ids, np.int64)
    known = ids[ids != 0]
    vectors = np.asarray(classes.vectors, np.float64)[ids != 0]
    out = []
    for labels in images:
        weighted = patch_class_histograms(labels, rows, cols, known) @ vectors
        norm = np.linalg.norm(weighted, axis=-1, keepdims=True)
        out.append(np.where(norm > 0, weighted / np.where(norm > 0, norm, 1.0), 0.0))
    return np.asarray(out, np.float32)
