"""Points on a triangle mesh: barycentrics and shading normals, with one rule for degenerate cases
(pure NumPy; used by the renderer, the samples stage and relight through pipeline.raycast).

* Barycentrics of points in their triangles (Ericson, Real-Time Collision Detection, 3.4):
  clipped at 0 and renormalized, since a ray hit lies inside its triangle up to rounding; a
  degenerate (zero-area) triangle has none, and its points get the centroid's (1/3, 1/3, 1/3).
* The shading normal is the barycentric interpolation of the vertex normals, normalized; where the
  vertex normals cancel (|n| <= 1e-6: a crease of opposite faces, a non-manifold fold) it is the
  face's geometric normal.
* Ray origins on the surface are lifted off it so that they do not hit their own triangle: a
  point on a face along the face normal by 1e-5 of the mesh's diagonal (POINT_LIFT), a vertex along
  its vertex normal by 1e-4 (VERTEX_LIFT: a vertex normal leaves the faces around a concave vertex
  at an angle, so it needs the larger lift).
"""

from __future__ import annotations

import numpy as np

DEGENERATE_NORMAL = 1e-6  # interpolated vertex normals shorter than this fall back to the face normal
POINT_LIFT = 1e-5  # ray origins on a face: lifted along the face normal by this x the mesh's diagonal
VERTEX_LIFT = 1e-4  # ray origins at a vertex: lifted along the vertex normal by this x the diagonal


def lifted(points: np.ndarray, normals: np.ndarray, diagonal: float, lift: float) -> np.ndarray:
    """Ray origins (N, 3): ``points`` moved along unit ``normals`` by ``lift`` (POINT_LIFT or
    VERTEX_LIFT) x the mesh's ``diagonal``."""
    return np.asarray(points, float) + np.asarray(normals, float) * (lift * diagonal)


def barycentric(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Barycentrics (N, 3) of points (N, 3) in their triangles (N, 3, 3), by the rule above."""
    triangles, points = np.asarray(triangles, float), np.asarray(points, float)
    if len(points) == 0:
        return np.zeros((0, 3))
    a = triangles[:, 0]
    e1, e2, d = triangles[:, 1] - a, triangles[:, 2] - a, points - a
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    d1, d2 = (d * e1).sum(1), (d * e2).sum(1)
    denom = d11 * d22 - d12 * d12
    ok = denom > 1e-30 * np.maximum(d11 * d22, 1e-300)
    safe = np.where(ok, denom, 1.0)
    v, w = (d22 * d1 - d12 * d2) / safe, (d11 * d2 - d12 * d1) / safe
    bary = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    total = bary.sum(axis=1, keepdims=True)
    bary = bary / np.where(total > 0, total, 1.0)
    return np.where((ok & (total[:, 0] > 0))[:, None], bary, 1.0 / 3.0)


def interpolated_normals(
    vertex_normals: np.ndarray, face_normals: np.ndarray, faces: np.ndarray, face_ids: np.ndarray, bary: np.ndarray
) -> np.ndarray:
    """Unit shading normals (N, 3) at points given by face ids (N,) and barycentrics (N, 3) on a mesh
    with vertex normals (V, 3), face normals (F, 3) and faces (F, 3) vertex ids, by the rule above."""
    face_ids = np.asarray(face_ids, np.int64)
    n = np.einsum("pk,pkc->pc", bary, np.asarray(vertex_normals, float)[np.asarray(faces)[face_ids]])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > DEGENERATE_NORMAL, n / np.maximum(length, 1e-300), np.asarray(face_normals, float)[face_ids])
