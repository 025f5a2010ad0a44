"""Rigging helpers shared by the procedural hand and head.

* :func:`joint_regressor`: non-negative, sum-to-one vertex weights whose
  weighted mean is exactly a target joint (maximum-entropy tilt of a
  Gaussian prior), so ``J_regressor @ v_template`` returns the designed joints.
* :func:`softmin_weights`: smooth skinning weights from distances to bones.
* :func:`segment_distance`: point-to-segment distances (bones as segments).
* :func:`axis_corrective`: pose-corrective blend shapes for a hinge axis,
  written as the linear map from the (R - I) pose feature.
* :func:`smooth_weights`: Laplacian smoothing of skinning weights on the mesh.
* :func:`smoothstep`, :func:`orthonormal_completion`: small numeric helpers.
"""

from __future__ import annotations

import numpy as np


def _maxent_row(points: np.ndarray, prior: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Weights w >= 0, sum 1, sum_i w_i p_i = target, closest (KL) to ``prior``.

    Newton's method on the convex dual ``log sum_i prior_i exp(lam . (p_i - t))``;
    the target must lie inside the convex hull of the supported points.
    """
    scale = float(np.abs(points - target).max())
    x = (points - target) / scale
    log_prior = np.log(prior)
    lam = np.zeros(3)

    def dual(lam_: np.ndarray) -> tuple[float, np.ndarray]:
        """Dual objective and the tilted weights it induces."""
        z = log_prior + x @ lam_
        e = np.exp(z - z.max())
        return float(z.max() + np.log(e.sum())), e / e.sum()

    value, w = dual(lam)
    for _ in range(100):
        grad = w @ x
        if np.linalg.norm(grad) < 1e-13:
            break
        centred = x - grad
        hess = (centred * w[:, None]).T @ centred + 1e-12 * np.eye(3)
        step = np.linalg.solve(hess, grad)
        t = 1.0
        while True:
            new_value, new_w = dual(lam - t * step)
            if new_value <= value - 1e-4 * t * float(grad @ step) or t < 1e-10:
                break
            t *= 0.5
        lam, value, w = lam - t * step, new_value, new_w
    if np.linalg.norm(w @ x) * scale > 1e-9:
        raise ValueError(f"joint target {target.tolist()} lies outside the hull of its regressor vertices")
    return w


def joint_regressor(vertices: np.ndarray, targets: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """vertices (V, 3), targets (J, 3), sigmas (J,) -> J_regressor (J, V).

    Row j is supported on vertices within ``4 sigma_j`` of target j (Gaussian
    prior of width sigma_j) and reproduces target j exactly on ``vertices``.
    """
    rows = np.zeros((targets.shape[0], vertices.shape[0]))
    for j, (target, sigma) in enumerate(zip(targets, sigmas)):
        d2 = ((vertices - target) ** 2).sum(axis=1)
        support = np.flatnonzero(d2 < (4.0 * sigma) ** 2)
        prior = np.exp(-0.5 * d2[support] / sigma**2)
        rows[j, support] = _maxent_row(vertices[support], prior / prior.sum(), target)
    return rows


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """points (V, 3), segment a-b (3,) each -> distances (V,)."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / max(float(ab @ ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def softmin_weights(distances: np.ndarray, allowed: np.ndarray, tau: float) -> np.ndarray:
    """distances (V, J) to each joint's bone, allowed (V, J) bool -> weights (V, J).

    ``w_j ∝ exp(-(d_j - min_k d_k) / tau)`` over the allowed joints: one joint
    dominates away from joints and neighbours blend over about ``+-r`` (bone
    radius r) around each joint. Rows sum to one.
    """
    d = np.where(allowed, distances, np.inf)
    logits = -(d - d.min(axis=1, keepdims=True)) / tau
    w = np.where(allowed, np.exp(logits), 0.0)
    w[w < 1e-6] = 0.0
    return w / w.sum(axis=1, keepdims=True)


def axis_corrective(delta_sym: np.ndarray, delta_asym: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Pose correctives of one joint as its (V, 3, 9) block of ``posedirs``.

    For a rotation by phi about the unit ``axis`` (``R - I = sin(phi) K + (1 - cos(phi)) K^2``
    with ``K = [axis]_x``) the block yields ``(1 - cos(phi)) delta_sym + sin(phi) delta_asym``
    (both (V, 3)); rotations about other axes give proportionally smaller responses.
    """
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    k2 = k @ k
    # (1 - cos) = <K^2, R - I> / 2 and sin = <K, R - I> / 2 (Frobenius products).
    return 0.5 * (delta_sym[:, :, None] * k2.reshape(1, 1, 9) + delta_asym[:, :, None] * k.reshape(1, 1, 9))


def smoothstep(edge0: float | np.ndarray, edge1: float | np.ndarray, x: np.ndarray) -> np.ndarray:
    """Cubic Hermite step from 0 at ``edge0`` to 1 at ``edge1`` (either order); the edges may be arrays that
    broadcast against ``x``."""
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def orthonormal_completion(leading: np.ndarray) -> np.ndarray:
    """(K, n) leading directions -> (n, n) orthonormal rows whose first K rows span
    the leading directions in order (Gram-Schmidt via QR, signs kept)."""
    n = leading.shape[1]
    q, r = np.linalg.qr(np.concatenate((leading, np.eye(n))).T)
    signs = np.sign(np.diag(r))
    signs[signs == 0] = 1.0
    return (q * signs).T[:n]


def smooth_weights(weights: np.ndarray, faces: np.ndarray, allowed: np.ndarray, iterations: int) -> np.ndarray:
    """Laplacian smoothing of skinning weights (V, J) over the mesh edges, keeping
    each vertex to its allowed joints (V, J) and rows summing to one."""
    n = weights.shape[0]
    edges = np.concatenate([faces[:, [a, b]] for a, b in ((0, 1), (1, 2), (2, 0))])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    degree = np.bincount(edges.ravel(), minlength=n)[:, None].astype(np.float64)
    w = weights
    for _ in range(iterations):
        neighbour_sum = np.zeros_like(w)
        np.add.at(neighbour_sum, edges[:, 0], w[edges[:, 1]])
        np.add.at(neighbour_sum, edges[:, 1], w[edges[:, 0]])
        w = np.where(allowed, 0.5 * w + 0.5 * neighbour_sum / degree, 0.0)
        w /= w.sum(axis=1, keepdims=True)
    return w
