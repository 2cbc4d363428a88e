"""The pinhole camera (pixel centres at integer coordinates) and the ray grids."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxloc.camera import Camera, patch_grid, stride_grid


def _project(camera: Camera, d: np.ndarray) -> np.ndarray:
    """Pixel coordinates (..., 2) of camera-frame directions, by the pinhole model."""
    return np.stack(
        [
            camera.fx * d[..., 0] / d[..., 2] + camera.cx,
            camera.fy * d[..., 1] / d[..., 2] + camera.cy,
        ],
        -1,
    )


def _patch_of_pixel(u, v, width, height, rows, cols):
    """Independent patch index: patch (r, c) spans columns [c W / cols, (c + 1) W / cols) of the
    continuous image whose pixel (u, v) covers [u - 0.5, u + 0.5)."""
    c = np.floor((u + 0.5) / (width / cols)).astype(int)
    r = np.floor((v + 0.5) / (height / rows)).astype(int)
    return r * cols + c


def test_principal_point_ray_is_the_optical_axis():
    cam = Camera(500.0, 480.0, 319.5, 239.5, 640, 480)
    np.testing.assert_array_equal(np.asarray(cam.directions(jnp.array([319.5, 239.5]))), [0, 0, 1])
    # Pixel centres are integers: the centre of the top-left pixel is (0, 0).
    d = np.asarray(cam.directions(jnp.array([0.0, 0.0])))
    np.testing.assert_allclose(d / d[2], [-319.5 / 500, -239.5 / 480, 1], rtol=1e-6)


def test_directions_are_unit_and_reproject_to_their_pixels():
    cam = Camera(400.0, 420.0, 300.0, 200.0, 640, 400)
    uv = np.random.default_rng(0).uniform([-0.5, -0.5], [639.5, 399.5], (500, 2)).astype(np.float32)
    d = np.asarray(cam.directions(jnp.asarray(uv)))
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
    assert np.all(d[:, 2] > 0)  # in front of the camera (z forward)
    np.testing.assert_allclose(_project(cam, d), uv, atol=2e-3)
    # x right, y down: a pixel right of and below the principal point has x > 0, y > 0.
    right_down = np.asarray(cam.directions(jnp.array([400.0, 300.0])))
    assert right_down[0] > 0 and right_down[1] > 0


def test_from_fov_edges_span_the_field_of_view():
    cam = Camera.from_fov(960, 540, 60.0)
    assert cam.cx == pytest.approx(479.5) and cam.cy == pytest.approx(269.5) and cam.fx == cam.fy
    # The outer edges of the image (u = -0.5 and u = W - 0.5) are at +-hfov / 2.
    left = np.asarray(cam.directions(jnp.array([-0.5, 269.5])))
    right = np.asarray(cam.directions(jnp.array([959.5, 269.5])))
    assert np.degrees(np.arctan2(left[0], left[2])) == pytest.approx(-30.0, abs=1e-4)
    assert np.degrees(np.arctan2(right[0], right[2])) == pytest.approx(30.0, abs=1e-4)


def test_stride_grid_on_the_reference_image():
    cam = Camera.from_fov(960, 540, 60.0)
    grid = stride_grid(cam, 20)
    uv, patch = np.asarray(grid.uv), np.asarray(grid.patch)
    assert grid.shape == (27, 48) and uv.shape == (27 * 48, 2) and grid.num_patches == 144
    assert (grid.rows, grid.cols) == (9, 16)
    np.testing.assert_array_equal(uv[0], [10, 10])
    np.testing.assert_array_equal(uv[-1], [950, 530])
    np.testing.assert_array_equal(uv, np.round(uv))  # integer pixel centres
    # Row-major over the (h, w) ray image.
    np.testing.assert_array_equal(uv[:48, 1], 10)
    np.testing.assert_array_equal(uv[48, :], [10, 30])
    np.testing.assert_array_equal(patch, _patch_of_pixel(uv[:, 0], uv[:, 1], 960, 540, 9, 16))
    np.testing.assert_array_equal(np.bincount(patch, minlength=144), 9)  # 3 x 3 rays per patch


def test_stride_one_is_every_pixel():
    cam = Camera.from_fov(32, 18, 70.0)
    grid = stride_grid(cam, 1, rows=3, cols=4)
    uv = np.asarray(grid.uv)
    assert grid.shape == (18, 32) and uv.shape == (18 * 32, 2)
    vv, uu = np.meshgrid(np.arange(18), np.arange(32), indexing="ij")
    np.testing.assert_array_equal(uv, np.stack([uu.ravel(), vv.ravel()], -1))
    np.testing.assert_array_equal(np.bincount(np.asarray(grid.patch)), 48)  # 8 x 6 px patches


def test_patch_grid_centres_and_indices():
    cam = Camera.from_fov(960, 540, 60.0)
    grid = patch_grid(cam, 9, 16)
    uv, patch = np.asarray(grid.uv), np.asarray(grid.patch)
    assert uv.shape == (144, 2) and grid.shape == (9, 16)
    np.testing.assert_array_equal(patch, np.arange(144))
    # Patch (r, c) centre: ((c + 0.5) * 60 - 0.5, (r + 0.5) * 60 - 0.5) in pixel coordinates.
    r, c = np.divmod(np.arange(144), 16)
    np.testing.assert_allclose(uv, np.stack([(c + 0.5) * 60 - 0.5, (r + 0.5) * 60 - 0.5], -1))
    sub = patch_grid(cam, 9, 16, rays_per_side=2)
    assert np.asarray(sub.uv).shape == (576, 2) and sub.shape == (18, 32)
    sub_patch = np.asarray(sub.patch)
    np.testing.assert_array_equal(np.bincount(sub_patch), 4)
    suv = np.asarray(sub.uv)
    np.testing.assert_array_equal(sub_patch, _patch_of_pixel(suv[:, 0], suv[:, 1], 960, 540, 9, 16))
    np.testing.assert_allclose(np.unique(suv[:, 0])[:2], [15 - 0.5, 45 - 0.5])


@pytest.mark.parametrize("rows,cols,stride", [(3, 7, 3), (5, 4, 7), (1, 1, 11)])
def test_each_ray_lies_inside_its_patch_for_uneven_sizes(rows, cols, stride):
    cam = Camera(90.0, 90.0, 49.5, 24.5, 100, 50)
    for grid in (stride_grid(cam, stride, rows, cols), patch_grid(cam, rows, cols, 3)):
        uv, patch = np.asarray(grid.uv), np.asarray(grid.patch)
        r, c = np.divmod(patch, cols)
        assert np.all((uv[:, 0] + 0.5 >= c * 100 / cols) & (uv[:, 0] + 0.5 < (c + 1) * 100 / cols))
        assert np.all((uv[:, 1] + 0.5 >= r * 50 / rows) & (uv[:, 1] + 0.5 < (r + 1) * 50 / rows))
        assert set(np.unique(patch)) == set(range(rows * cols))


def test_camera_is_a_pytree_that_jits_and_vmaps():
    cam = Camera.from_fov(64, 48, 60.0)
    uv = jnp.asarray(np.random.default_rng(0).uniform(0, 40, (3, 5, 2)), jnp.float32)
    eager = np.asarray(cam.directions(uv))
    jitted = np.asarray(jax.jit(lambda c, x: c.directions(x))(cam, uv))
    vmapped = np.asarray(jax.vmap(cam.directions)(uv))
    np.testing.assert_allclose(jitted, eager, atol=1e-7)
    np.testing.assert_allclose(vmapped, eager, atol=1e-7)


def test_bad_cameras_and_grids_raise():
    with pytest.raises(ValueError, match="fx must be positive"):
        Camera(0.0, 1.0, 0.0, 0.0, 4, 4)
    with pytest.raises(ValueError, match="cy must be finite"):
        Camera(1.0, 1.0, 0.0, float("nan"), 4, 4)
    with pytest.raises(TypeError, match="Python ints"):
        Camera(1.0, 1.0, 0.0, 0.0, 4.0, 4)
    with pytest.raises(ValueError, match="size must be positive"):
        Camera(1.0, 1.0, 0.0, 0.0, 0, 4)
    cam = Camera.from_fov(64, 48, 60.0)
    with pytest.raises(ValueError, match="stride"):
        stride_grid(cam, 0)
    with pytest.raises(ValueError, match=">= 1"):
        patch_grid(cam, 0, 4)
