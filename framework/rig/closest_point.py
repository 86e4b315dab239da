"""Exact closest points on a triangle mesh for many query points, vectorised (numpy, float64).

trimesh's `proximity.closest_point` is exact but costs ~1 ms per point here (measured 4.3 s for 5k queries on a
20k-face sphere), far too slow for a 64^3 grid. This module gets the same answer faster: candidate triangles come from
a KD-tree over triangle centroids, the exact point-triangle distance (Ericson, Real-Time Collision Detection 5.1.5) is
evaluated for them, and the result is *certified*: a triangle whose centroid is farther than d_best + r_max (r_max the
largest centroid-to-vertex radius) cannot be closer, so a query whose k-th candidate centroid lies beyond that bound
is exact. Uncertified queries are retried with 4x more candidates, ending in brute force over all triangles.
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
        new = np.stack([np.broadcast_to(u0, mask.shape), np.broadcast_to(u1, mask.shape),
                        np.broadcast_to(u2, mask.shape)], axis=-1)  # fmt: skip
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
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, k: int = 16, chunk: int = 1 << 20
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact closest triangle for each query point.

    vertices [V, 3], faces [F, 3], points [Q, 3] -> face index [Q], barycentric coordinates [Q, 3], distance [Q].
    `chunk` bounds the number of (point, candidate) pairs evaluated at once (memory).
    """
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    nf, nq = f.shape[0], p.shape[0]
    if nf == 0:
        raise ValueError("closest_points: the mesh has no faces.")
    tri = v[f]  # [F, 3, 3]
    centroid = tri.mean(1)
    r_max = float(np.sqrt(((tri - centroid[:, None]) ** 2).sum(-1)).max())
    tree = cKDTree(centroid)
    face = np.zeros(nq, dtype=np.int64)
    bary = np.zeros((nq, 3))
    dist = np.full(nq, np.inf)
    todo = np.arange(nq)
    kk = min(k, nf)
    while todo.size:
        step = max(1, chunk // kk)
        certified = []
        for s in range(0, todo.size, step):
            idx = todo[s : s + step]
            if kk >= nf:
                cand = np.broadcast_to(np.arange(nf), (idx.size, nf))
                far = np.full(idx.size, np.inf)
            else:
                cd, cand = tree.query(p[idx], k=kk)
                cand, far = cand.reshape(idx.size, kk), cd.reshape(idx.size, kk)[:, -1]
            t = tri[cand]  # [q, kk, 3, 3]
            bc, d2 = closest_on_triangles(p[idx, None], t[:, :, 0], t[:, :, 1], t[:, :, 2])
            best = d2.argmin(1)
            rows = np.arange(idx.size)
            face[idx] = cand[rows, best]
            bary[idx] = bc[rows, best]
            dist[idx] = np.sqrt(d2[rows, best])
            certified.append(far >= dist[idx] + r_max)
        ok = np.concatenate(certified)
        todo = todo[~ok]
        kk = min(kk * 4, nf)
    return face, bary, dist
