"""Described maps on disk: :func:`save_triplet_map` / :func:`load_triplet_map`, and
:func:`open_triplet_map`, the described map of a saved file or of an instance-map folder.

One compressed ``.npz`` holds every array of a :class:`TripletMap` (vertices, class positions, the
descriptors of every scale, RSN cells) and its :class:`TripletConfig` as JSON text, with a format
name and version. Loading never unpickles (``allow_pickle=False``) and validates everything before
a map is built: format and version, the configuration (through the config classes' own checks),
dtypes, shapes that agree with each other and the configuration, finite values, class positions in
range, unit descriptors where valid and zeros elsewhere, unit normals, positive sigmas. Writes are
atomic (temporary file, then rename).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from jaxloc._lazy import renamed_names
from jaxloc.compilation_cache import cache_entry
from jaxloc.io._atomic import write_npz_atomic
from jaxloc.io._map_file import read_map_file
from jaxloc.io.errors import MapFormatError
from jaxloc.io.instance_maps import read_lidar_map
from jaxloc.lsq import RobustLoss
from jaxloc.m2loc import (
    DescriptorConfig,
    TripletConfig,
    TripletMap,
    build_map,
    m2loc_config,
    prepare_queries,
)
from jaxloc.m2loc._hypotheses import host_map_grid
from jaxloc.m2loc._map import fit_config_to_map, triplet_map_spec

#: The ``format`` entry of a triplet-map file (a file without it is refused).
FORMAT_NAME = "jaxloc.TripletMap"
#: The triplet-map file version this module writes and reads.
TRIPLET_MAP_FORMAT_VERSION = 1

# name: (dtype, shape with -1 for "any"; N vertices, S scales, D dim, M RSN cells checked after)
_ARRAYS = {
    "points": (np.float32, (-1, 3)),
    "classes": (np.int32, (-1,)),
    "descriptors": (np.float32, (-1, -1, -1)),
    "valid": (np.bool_, (-1, -1)),
    "origin": (np.float32, (3,)),
    "rsn_xy": (np.float32, (-1, 2)),
    "rsn_normals": (np.float32, (-1, 3)),
    "rsn_sigma": (np.float32, (-1,)),
    "has_rsn": (np.bool_, ()),
}

_NESTED = {"descriptor": DescriptorConfig, "loss": RobustLoss}


def _config_to_dict(module) -> dict:
    out = {}
    for field in dataclasses.fields(module):
        value = getattr(module, field.name)
        if field.name in _NESTED:
            value = _config_to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        elif isinstance(value, np.ndarray | jax.Array):
            value = value.item()
        out[field.name] = value
    return out


def _config_from_dict(cls, values: dict):
    if not isinstance(values, dict):
        raise TypeError(f"{cls.__name__} must be a JSON object, got {type(values).__name__}")
    names = {field.name for field in dataclasses.fields(cls)}
    unknown = set(values) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields {sorted(unknown)}")
    kwargs = {}
    for name, value in values.items():
        if name in _NESTED:
            value = _config_from_dict(_NESTED[name], value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def save_triplet_map(triplet_map: TripletMap, path: str | os.PathLike) -> None:
    """Write a described map (every array and its configuration) to one versioned ``.npz``,
    atomically. :func:`load_triplet_map` gives back identical arrays."""
    arrays = {name: np.asarray(getattr(triplet_map, name)) for name in _ARRAYS if name != "has_rsn"}
    arrays["has_rsn"] = np.array(triplet_map.has_rsn)
    arrays["format"] = np.array(FORMAT_NAME)
    arrays["version"] = np.array(TRIPLET_MAP_FORMAT_VERSION, np.int64)
    arrays["config"] = np.array(json.dumps(_config_to_dict(triplet_map.config)))
    write_npz_atomic(path, arrays)


def _check_arrays(path: Path, content: dict[str, np.ndarray], config: TripletConfig) -> None:
    for name, (dtype, shape) in _ARRAYS.items():
        if name not in content:
            raise MapFormatError(f"{path}: missing array '{name}'")
        array = content[name]
        if array.dtype != dtype:
            raise MapFormatError(f"{path}: '{name}' has dtype {array.dtype}, expected {dtype}")
        if array.ndim != len(shape) or any(
            want not in (-1, got) for want, got in zip(shape, array.shape, strict=True)
        ):
            raise MapFormatError(f"{path}: '{name}' has shape {array.shape}")
        if np.issubdtype(array.dtype, np.floating) and not np.all(np.isfinite(array)):
            raise MapFormatError(f"{path}: '{name}' contains NaN or inf")
    n = content["points"].shape[0]
    scales, dim = config.descriptor.num_scales, config.descriptor.dim
    m = content["rsn_xy"].shape[0]
    descriptors, valid = content["descriptors"], content["valid"]
    norms = np.linalg.norm(descriptors, axis=-1)
    classes = content["classes"]
    checks = [
        (n >= 3, f"{n} vertices (at least 3 needed)"),
        (classes.shape == (n,), "'classes' does not match 'points'"),
        (
            np.all((classes >= 0) & (classes < len(config.descriptor.classes))),
            "class positions out of range",
        ),
        (descriptors.shape == (scales, n, dim), f"'descriptors' is not ({scales}, {n}, {dim})"),
        (valid.shape == (scales, n), f"'valid' is not ({scales}, {n})"),
        (
            descriptors.shape != (scales, n, dim)
            or valid.shape != (scales, n)
            or (np.allclose(norms[valid], 1.0, atol=1e-3) and not np.any(norms[~valid])),
            "descriptors are not unit vectors where valid and zero elsewhere",
        ),
        (m >= 1, "no RSN cell (a map without normals keeps one dummy cell)"),
        (content["rsn_normals"].shape[0] == m, "'rsn_normals' does not match 'rsn_xy'"),
        (content["rsn_sigma"].shape == (m,), "'rsn_sigma' does not match 'rsn_xy'"),
        (
            np.allclose(np.linalg.norm(content["rsn_normals"], axis=-1), 1.0, atol=1e-3),
            "road normals are not unit vectors",
        ),
        (np.all(content["rsn_sigma"] > 0), "RSN sigmas must be > 0"),
    ]
    for ok, message in checks:
        if not ok:
            raise MapFormatError(f"{path}: {message}")


def load_triplet_map(path: str | os.PathLike) -> TripletMap:
    """Load and validate a map written by :func:`save_triplet_map` (never unpickles).

    Raises:
        FileNotFoundError: no such file.
        MapFormatError: a corrupt, truncated or foreign file, another format version, a bad
            configuration, or arrays with wrong dtypes or shapes, NaN/inf or inconsistent values.

    Warns:
        SmallMapWarning: the saved ``top_k`` exceeds the map's vertices (it is clamped).
    """
    path = Path(path)
    content = read_map_file(path, FORMAT_NAME, TRIPLET_MAP_FORMAT_VERSION, "triplet map")
    try:
        config = _config_from_dict(TripletConfig, json.loads(str(content["config"])))
    except Exception as err:  # JSON, unknown fields, wrong types, config checks
        raise MapFormatError(f"{path}: bad configuration ({err})") from err
    _check_arrays(path, content, config)
    config = fit_config_to_map(config, content["points"].shape[0], stacklevel=2)
    # device_put, not jnp.asarray: no conversion program compiled per array shape
    arrays = {name: jax.device_put(content[name]) for name in _ARRAYS if name != "has_rsn"}
    grid = host_map_grid(content["points"], content["classes"], float(config.verify_radius))
    return TripletMap(**arrays, has_rsn=bool(content["has_rsn"]), config=config, grid=grid)


def open_triplet_map(
    path: str | os.PathLike,
    config: TripletConfig | None = None,
    *,
    replace: Mapping[str, object] | None = None,
    query_capacities: Sequence[int] = (),
) -> TripletMap:
    """The described map at ``path``: a file saved by :func:`save_triplet_map` (loaded in about a
    second), or an instance-map folder (``instances/<class>.txt`` and, with ``config.use_rsn``,
    ``RSN/road_normal.txt`` when present; :func:`~jaxloc.io.instance_maps.read_lidar_map`)
    described with ``config`` (default ``m2loc_config(3)``).

    Args:
        path: the ``.npz`` file or the map folder.
        config: the folder's configuration (a saved map keeps the one it was described with).
        replace: :class:`~jaxloc.m2loc.TripletConfig` fields to change that do not change the
            descriptors (``top_k``, ``min_clique``, ``use_rsn``...), applied to either
            configuration; ``top_k`` is then fitted to the map
            (``fit_config_to_map``).
        query_capacities: padded scan sizes (``query_capacity``) whose query
            programs compile in the background while a folder is described
            (:func:`~jaxloc.m2loc.prepare_queries`; with the compilation cache on).

    Raises:
        FileNotFoundError: no such file or folder, a missing class file.
        ValueError: naming the file or folder: a corrupt map file (:class:`MapFormatError`), a
            ``config`` given with a saved map, a setting the map cannot take, malformed files.

    Warns:
        SmallMapWarning: ``top_k`` exceeds the map's vertices (it is clamped).
    """
    path = Path(path)
    replace = dict(replace or {})
    if not path.is_file():
        config = dataclasses.replace(config or m2loc_config(3), **replace)
        instances, normals = read_lidar_map(path, config.descriptor.classes, config.use_rsn)
        if query_capacities:
            try:
                spec = triplet_map_spec(instances.points, instances.labels, config, normals)
            except ValueError:  # a map build_map refuses: its error, below, and nothing compiled
                spec = None
            if spec is not None:
                prepare_queries(spec, query_capacities)
        kept = _kept_map_file(instances.points, instances.labels, normals, config)
        triplet_map = _load_kept_map(kept, config) if kept is not None else None
        if triplet_map is None:
            try:
                triplet_map = build_map(instances.points, instances.labels, config, normals)
            except ValueError as error:
                raise ValueError(f"map {path}: {error}") from error
            if kept is not None:
                try:
                    save_triplet_map(triplet_map, kept)
                except OSError:  # a cache that cannot be written costs the next run a description
                    pass
        return triplet_map
    if config is not None:
        raise ValueError(f"{path}: a saved map keeps the configuration it was described with")
    triplet_map = load_triplet_map(path)  # its errors name the file
    try:
        config = dataclasses.replace(triplet_map.config, **replace)
        config = fit_config_to_map(config, int(triplet_map.points.shape[0]), stacklevel=2)
    except ValueError as error:  # a setting the map cannot take
        raise ValueError(f"{path}: {error}") from error
    return eqx.tree_at(lambda m: m.config, triplet_map, config)


def _kept_map_file(points, labels, normals, config: TripletConfig) -> Path | None:
    """Where the compilation cache keeps the described map of these instances (None when the
    cache is off): keyed by the vertices, labels, road normals and every setting of ``config``
    (its tree structure, static settings included, and its array values)."""
    rsn = () if normals is None else tuple(np.asarray(a) for a in normals)
    settings = [np.asarray(leaf) for leaf in jax.tree.leaves(config)]
    return cache_entry(
        "maps",
        ".npz",
        TRIPLET_MAP_FORMAT_VERSION,
        np.asarray(points),
        np.asarray(labels),
        *rsn,
        str(jax.tree.structure(config)),
        *settings,
    )


def _load_kept_map(file: Path, config: TripletConfig) -> TripletMap | None:
    """The described map kept in the cache, with ``config`` fitted to it as :func:`build_map`
    does (the same SmallMapWarning); None if there is none or it does not load (described
    again)."""
    if not file.is_file():
        return None
    try:
        kept = load_triplet_map(file)
    except (OSError, ValueError):
        return None
    fitted = fit_config_to_map(config, int(kept.points.shape[0]), stacklevel=3)
    return eqx.tree_at(lambda m: m.config, kept, fitted)


#: The constant's name in jaxloc 0.2; it resolves, with a DeprecationWarning, until 0.4.
__getattr__ = renamed_names(__name__, {"FORMAT_VERSION": "TRIPLET_MAP_FORMAT_VERSION"})
