"""One ray against one triangle (Moller-Trumbore), coordinates written out.

The kernels take coordinates as lists of 3 arrays of any (broadcastable) shape ``...`` instead of
(..., 3) rows: on (R,) columns XLA:CPU runs them about 2x faster than a vmap over rows, and the
traversal broadcasts one ray against a leaf's K triangles with the same code.
"""

from __future__ import annotations

import jax.numpy as jnp

#: Hits closer than this (metres) are ignored, so a ray leaving a surface does not hit it again.
T_MIN = 1e-6
#: Moller-Trumbore determinant below which a ray counts as parallel to the triangle.
DET_EPS = 1e-12
#: Barycentric slack of the acceptance test: float32 rounding of u and v must not let a ray through
#: an edge shared by two triangles miss both (a "leak" through a closed surface). Triangles grow by
#: this fraction of their size, which is far below the meshes' accuracy.
EDGE_EPS = 1e-5
#: Rays in flight in the traversal loop (lanes x packet size): enough lanes to amortise the loop's


def moller_trumbore(o, d, v0, e1, e2):
    """One ray vs triangles given as (3, ...) coordinate arrays; returns t, u, v, det (...)."""
    px = d[1] * e2[2] - d[2] * e2[1]
    py = d[2] * e2[0] - d[0] * e2[2]
    pz = d[0] * e2[1] - d[1] * e2[0]
    det = e1[0] * px + e1[1] * py + e1[2] * pz
    inv = 1.0 / jnp.where(jnp.abs(det) > DET_EPS, det, 1.0)
    sx, sy, sz = o[0] - v0[0], o[1] - v0[1], o[2] - v0[2]
    u = (sx * px + sy * py + sz * pz) * inv
    qx = sy * e1[2] - sz * e1[1]
    qy = sz * e1[0] - sx * e1[2]
    qz = sx * e1[1] - sy * e1[0]
    v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv
    t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv
    return t, u, v, det


def triangle_hit(o, d, v0, e1, e2):
    """Moller-Trumbore with the acceptance test; t is +inf where the ray misses."""
    t, u, v, det = moller_trumbore(o, d, v0, e1, e2)
    inside = (u >= -EDGE_EPS) & (v >= -EDGE_EPS) & (u + v <= 1.0 + EDGE_EPS)
    hit = (jnp.abs(det) > DET_EPS) & inside & (t > T_MIN)
    return jnp.where(hit, t, jnp.inf)
