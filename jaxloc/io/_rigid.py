"""Host-side check that 4x4 matrices read from user files are rigid transforms."""

from __future__ import annotations

import numpy as np

#: Tolerance on ``|R^T R - I|`` and ``|det R - 1|`` of a pose read from a text file.
RIGID_TOLERANCE = 1e-3


def rigid_mask(matrices: np.ndarray) -> np.ndarray:
    """Which of the (..., 4, 4) matrices are rigid: an orthonormal rotation with determinant +1
    (within :data:`RIGID_TOLERANCE`) and a last row ``0 0 0 1``. Returns a (...) bool array."""
    matrices = np.asarray(matrices, np.float64)
    rotation = matrices[..., :3, :3]
    gram = np.abs(np.swapaxes(rotation, -1, -2) @ rotation - np.eye(3)).max(axis=(-1, -2))
    determinant = np.abs(np.linalg.det(rotation) - 1.0)
    bottom = np.abs(matrices[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    return (gram <= RIGID_TOLERANCE) & (determinant <= RIGID_TOLERANCE) & (bottom <= 1e-6)
