"""Textured object meshes of the synthetic indoor world (host-side numpy/trimesh).

Each object's primitives (see :mod:`jaxloc.synthetic.indoor.furniture`) are refined by splitting the
largest triangles until the mesh holds a target number of vertices (the coarse 3RScan object meshes
average 863), then coloured per vertex: the part's base colour times a pattern (stripes, checker
or noise) of the local position, plus per-vertex noise, so patches have texture for SSIM. The
floor, ceiling and walls are planar grids of the same density.
"""

from __future__ import annotations

import numpy as np
import trimesh

from jaxloc.synthetic.indoor.furniture import FURNITURE, PAINT, WOOD, Part, pick


def _refine(vertices, faces, part_ids, target: int):
    """Split the largest triangles (midpoint subdivision) until about ``target`` vertices.

    Each pass splits at most a third of the missing count of faces (a split adds <= 3 vertices),
    so the result lies in ``[target, target + 2]`` unless the input already has more.
    """
    attributes = {"part": part_ids.astype(float)[:, None]}
    while len(vertices) < target:
        missing = target - len(vertices)
        order = np.argsort(-trimesh.triangles.area(vertices[faces]), kind="stable")
        vertices, faces, attributes = trimesh.remesh.subdivide(
            vertices, faces, face_index=order[: max(1, missing // 3)], vertex_attributes=attributes
        )
    return vertices, faces, np.rint(attributes["part"][:, 0]).astype(int)


def _pattern_values(rng: np.random.Generator, kind: str, points: np.ndarray) -> np.ndarray:
    """A texture value in [0, 1] per point (local coordinates, metres)."""
    if kind == "stripes":
        axis = np.eye(3)[rng.integers(3)] + rng.normal(0, 0.15, 3)
        period = rng.uniform(0.1, 0.35)
        return (np.sin(2 * np.pi * points @ axis / period + rng.uniform(0, 2 * np.pi)) > 0) * 1.0
    if kind == "checker":
        cells = np.floor(points / rng.uniform(0.08, 0.25)).astype(int)
        return (cells.sum(axis=1) % 2) * 1.0
    if kind == "noise":
        return rng.uniform(0, 1, len(points))
    return np.full(len(points), 0.5)


def _paint(rng, parts: list[Part], vertices, part_ids) -> np.ndarray:
    """Per-vertex RGB in [0, 1]: base colour x (1 + amplitude x (pattern - 0.5)) + noise."""
    colors = np.empty((len(vertices), 3))
    for index, part in enumerate(parts):
        mask = part_ids == index
        amplitude = 0.15 if part.pattern == "plain" else rng.uniform(0.35, 0.6)
        values = _pattern_values(rng, part.pattern, vertices[mask])
        shade = 1.0 + amplitude * (values - 0.5)
        colors[mask] = np.asarray(part.color) * shade[:, None]
    colors += rng.normal(0.0, 0.03, colors.shape)
    return np.clip(colors, 0.0, 1.0)


def assemble(rng: np.random.Generator, parts: list[Part], target_vertices: int) -> trimesh.Trimesh:
    """One textured mesh from its parts, refined to ``target_vertices`` (local frame)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets[:-1], strict=True)])
    part_ids = np.repeat(np.arange(len(parts)), np.diff(offsets))
    vertices, faces, part_ids = _refine(vertices, faces, part_ids, target_vertices)
    colors = _paint(rng, parts, vertices, part_ids)
    rgba = np.concatenate([np.rint(colors * 255), np.full((len(colors), 1), 255)], axis=1)
    return trimesh.Trimesh(vertices, faces, vertex_colors=rgba.astype(np.uint8), process=False)


def build_furniture(rng: np.random.Generator, class_index: int, size, target_vertices: int):
    """Mesh (local frame) of furniture class ``FURNITURE[class_index]`` with size (w, d, h)."""
    _, builder = FURNITURE[class_index]
    return assemble(rng, builder(rng, *size), target_vertices)


def _grid(origin, u, v, target_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """A planar grid of about ``target_vertices`` vertices spanning ``origin + [0,1]u + [0,1]v``,
    triangles facing ``u x v``."""
    lu, lv = np.linalg.norm(u), np.linalg.norm(v)
    nu = max(2, int(round(np.sqrt(target_vertices * lu / lv))))
    nv = max(2, int(round(target_vertices / nu)))
    a, b = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    vertices = origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    index = np.arange(nu * nv).reshape(nu, nv)
    p00, p10, p01, p11 = index[:-1, :-1], index[1:, :-1], index[:-1, 1:], index[1:, 1:]
    faces = np.concatenate(
        [np.stack([p00, p10, p11], -1).reshape(-1, 3), np.stack([p00, p11, p01], -1).reshape(-1, 3)]
    )
    return vertices, faces


def build_structure(
    rng: np.random.Generator, size, target_vertices
) -> list[tuple[str, trimesh.Trimesh]]:
    """Floor, ceiling and four walls of a room ``[0, Lx] x [0, Ly] x [0, H]``, facing inwards.

    ``target_vertices`` gives one vertex count per surface (6 values). Returns (class, mesh) pairs.
    """
    lx, ly, h = size
    z = np.array([0.0, 0.0, h])
    corners = [np.array(c, float) for c in ((0, 0, 0), (lx, 0, 0), (lx, ly, 0), (0, ly, 0))]
    surfaces = [
        ("floor", _grid(corners[0], corners[1], corners[3], target_vertices[0]), WOOD, "stripes"),
        ("ceiling", _grid(z, corners[3], corners[1], target_vertices[1]), PAINT[:1], "noise"),
    ]
    wall_color = pick(rng, PAINT)
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        grid = _grid(a, z, b - a, target_vertices[2 + k])
        surfaces.append(("wall", grid, (wall_color,), "stripes" if k % 2 else "noise"))
    meshes = []
    for name, (vertices, faces), palette, pattern in surfaces:
        part = Part(vertices, faces, tuple(pick(rng, palette)), pattern)
        colors = _paint(rng, [part], vertices, np.zeros(len(vertices), int))
        rgba = np.concatenate([np.rint(colors * 255), np.full((len(colors), 1), 255)], axis=1)
        meshes.append(
            (
                name,
                trimesh.Trimesh(
                    vertices, faces, vertex_colors=rgba.astype(np.uint8), process=False
                ),
            )
        )
    return meshes
