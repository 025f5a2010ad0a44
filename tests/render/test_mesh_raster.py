"""Tests of the supersampled mesh rasterizer against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar.render.mesh_raster import Mesh, PinholeCamera, render

W = H = 16
F = 20.0  # focal length in pixels


def _camera(width: int = W, height: int = H) -> PinholeCamera:
    k = np.array([[F, 0.0, width / 2], [0.0, F, height / 2], [0.0, 0.0, 1.0]])
    return PinholeCamera(K=k, world_to_cam=np.eye(4), width=width, height=height)


def _unproject(uv: np.ndarray, z: np.ndarray | float, width: int = W, height: int = H) -> np.ndarray:
    """Pixel coordinates (N, 2) at depth z -> camera/world points (N, 3)."""
    z = np.broadcast_to(np.asarray(z, dtype=np.float64), (uv.shape[0],))
    x = (uv[:, 0] - width / 2) * z / F
    y = (uv[:, 1] - height / 2) * z / F
    return np.stack([x, y, z], axis=1)


def _triangle(pixels: np.ndarray, z: float | np.ndarray = 1.0, colour=(1.0, 1.0, 1.0), label: int = 1) -> Mesh:
    verts = _unproject(pixels, z)
    return Mesh(
        vertices=verts,
        faces=np.array([[0, 1, 2]]),
        attributes=np.tile(np.asarray(colour, dtype=np.float32), (3, 1)),
        label=label,
    )


def _clip(poly: list[tuple[float, float]], axis: int, bound: float, keep_below: bool) -> list[tuple[float, float]]:
    """One Sutherland-Hodgman pass against the half-plane p[axis] <= / >= bound."""

    def inside(p):
        return p[axis] <= bound if keep_below else p[axis] >= bound

    def cross(p, q):
        t = (bound - p[axis]) / (q[axis] - p[axis])
        return (p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]))

    out: list[tuple[float, float]] = []
    for i, cur in enumerate(poly):
        prev = poly[i - 1]
        if inside(cur):
            if not inside(prev):
                out.append(cross(prev, cur))
            out.append(cur)
        elif inside(prev):
            out.append(cross(prev, cur))
    return out


def _area(poly: list[tuple[float, float]]) -> float:
    if len(poly) < 3:
        return 0.0
    p = np.asarray(poly)
    return 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))


def exact_coverage(tri: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) area of intersection of the triangle with each unit pixel square."""
    cov = np.zeros((height, width))
    for i in range(height):
        for j in range(width):
            poly = [tuple(p) for p in tri]
            for axis, bound, below in ((0, j, False), (0, j + 1, True), (1, i, False), (1, i + 1, True)):
                poly = _clip(poly, axis, bound, below)
                if not poly:
                    break
            cov[i, j] = _area(poly)
    return cov


TRI = np.array([[2.3, 1.7], [13.6, 4.2], [5.1, 14.4]])


@pytest.mark.parametrize("s", [2, 4, 8, 16])
def test_coverage_matches_polygon_clipping(s: int) -> None:
    exact = exact_coverage(TRI, W, H)
    out = render([_triangle(TRI)], _camera(), supersample=s)
    err = np.abs(out.alpha.numpy() - exact)
    # Each of the <= 3 edges in a pixel misclassifies at most ~(2s + 2) of its s^2 cells.
    assert err.max() <= 3 * (2 * s + 2) / s**2
    (ax, ay), (bx, by) = TRI[1] - TRI[0], TRI[2] - TRI[0]
    total = 0.5 * abs(ax * by - ay * bx)
    assert abs(out.alpha.sum().item() - total) < 0.05 * total
    # Colour is the coverage-weighted average over a black background.
    np.testing.assert_allclose(out.rgb.numpy(), np.repeat(out.alpha.numpy()[..., None], 3, -1), atol=1e-6)


def test_coverage_error_shrinks_with_supersampling() -> None:
    exact = exact_coverage(TRI, W, H)
    errs = [np.abs(render([_triangle(TRI)], _camera(), supersample=s).alpha.numpy() - exact).mean() for s in (2, 8, 16)]
    assert errs[2] < errs[1] < errs[0]
    assert errs[2] < 0.01


def test_nearer_triangle_wins() -> None:
    big = np.array([[0.0, 0.0], [32.0, 0.0], [0.0, 32.0]])
    far = _triangle(big, z=2.0, colour=(1.0, 0.0, 0.0), label=1)
    near = _triangle(big, z=1.0, colour=(0.0, 1.0, 0.0), label=2)
    for order in ([far, near], [near, far]):
        out = render(order, _camera(), supersample=2, max_samples_per_chunk=64)
        inner = out.alpha.numpy() == 1.0
        assert inner.sum() > 50
        np.testing.assert_allclose(out.rgb.numpy()[inner], [[0.0, 1.0, 0.0]] * int(inner.sum()))
        assert (out.labels.numpy()[inner] == 2).all()
        np.testing.assert_allclose(out.depth.numpy()[inner], 1.0, rtol=1e-5)


def test_perspective_correct_interpolation_on_a_plane() -> None:
    """A slanted plane z = 1 + 0.25 x carries the attribute x (world metres); at a
    pixel centre the ray meets the plane at a closed-form point."""
    uv = np.array([[-20.0, -20.0], [60.0, -20.0], [-20.0, 60.0]])
    rays = (uv - W / 2) / F  # x/z, y/z per vertex
    z = 1.0 / (1.0 - 0.25 * rays[:, 0])  # z = 1 + 0.25 x with x = z * rx
    verts = np.column_stack([rays * z[:, None], z])
    attr = verts.astype(np.float32)
    mesh = Mesh(vertices=verts, faces=np.array([[0, 1, 2]]), attributes=attr, label=1)
    out = render([mesh], _camera(), supersample=1)
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rx, ry = (jj - W / 2) / F, (ii - H / 2) / F
    z_true = 1.0 / (1.0 - 0.25 * rx)
    assert (out.alpha.numpy() == 1.0).all()
    np.testing.assert_allclose(out.depth.numpy(), z_true, rtol=1e-4)
    np.testing.assert_allclose(out.rgb.numpy()[..., 0], rx * z_true, atol=1e-4)
    np.testing.assert_allclose(out.rgb.numpy()[..., 1], ry * z_true, atol=1e-4)


@pytest.mark.parametrize("zs", [(-1.0, -1.0, -1.0), (1.0, -0.5, 2.0), (0.0, 1.0, 1.0), (1e-12, 1.0, 1.0)])
def test_triangles_behind_or_crossing_camera_give_no_nan(zs) -> None:
    verts = np.array([[0.1, 0.0, zs[0]], [-0.2, 0.3, zs[1]], [0.2, 0.2, zs[2]]])
    mesh = Mesh(vertices=verts, faces=np.array([[0, 1, 2]]), attributes=np.ones((3, 3), np.float32), label=1)
    out = render([mesh], _camera(), supersample=3)
    for t in (out.rgb, out.alpha, out.depth):
        assert torch.isfinite(t).all()
    assert out.alpha.sum() == 0


def test_degenerate_triangle_draws_nothing() -> None:
    colinear = np.array([[1.0, 1.0], [8.0, 8.0], [15.0, 15.0]])
    point = np.array([[5.5, 5.5]] * 3)
    out = render([_triangle(colinear), _triangle(point)], _camera(), supersample=4)
    assert out.alpha.sum() == 0
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()


def test_empty_scene_gives_background() -> None:
    bg = (0.2, 0.3, 0.4)
    out = render([], _camera(), supersample=2, background=bg)
    np.testing.assert_allclose(out.rgb.numpy(), np.broadcast_to(bg, (H, W, 3)), atol=1e-7)
    assert out.alpha.sum() == 0 and (out.labels == 0).all() and (out.depth == 0).all()


def test_labels_majority_and_shader_receive_labels() -> None:
    left = np.array([[0.0, 0.0], [8.0, 0.0], [8.0, 16.0]])
    right = np.array([[8.0, 0.0], [16.0, 0.0], [16.0, 16.0]])
    seen: list[torch.Tensor] = []

    def shader(attrs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        seen.append(labels)
        return labels[:, None].float().expand(-1, 3) / 10

    out = render([_triangle(left, label=1), _triangle(right, label=2)], _camera(), supersample=3, shader=shader)
    labels = out.labels.numpy()
    assert set(np.unique(labels)) == {0, 1, 2}
    assert (labels[out.alpha.numpy() < 0.5] == 0).all()
    assert set(torch.unique(seen[0]).tolist()) == {1, 2}
    full = out.alpha.numpy() == 1.0
    np.testing.assert_allclose(out.rgb.numpy()[full][:, 0], labels[full] / 10, atol=1e-6)
