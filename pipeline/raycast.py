"""The stages' ray casting against the capture's mesh (trimesh's Embree intersector, embreex):
first hits of camera rays as surface points — face, point, barycentrics, shading normal by
pipeline.core.surface's one rule — and occlusion tests.  Used by the samples stage and relight;
the renderer (pipeline.core.render) holds its own Embree scenes for shadow and bounce rays and
takes its surface points from the same pipeline.core.surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.surface import barycentric, interpolated_normals


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays: for the H rays that hit, their index in the batch (H,), the
    face (H,), the point (H, 3), barycentrics (H, 3) and the unit shading normal (H, 3)."""

    ray: np.ndarray
    face: np.ndarray
    point: np.ndarray
    bary: np.ndarray
    normal: np.ndarray


def intersector(mesh):
    """An Embree intersector of a trimesh mesh (build once per mesh; safe to share between threads)."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    return RayMeshIntersector(mesh)


def first_hits(mesh, rays, origins: np.ndarray, directions: np.ndarray) -> Hits:
    """The first hit of each ray (origins, unit directions (N, 3)) on ``mesh`` through ``rays``
    (intersector(mesh)); rays that miss are left out."""
    face, ray, point = rays.intersects_id(origins, directions, multiple_hits=False, return_locations=True)
    face, ray = np.asarray(face, np.int64), np.asarray(ray, np.int64)
    point = np.asarray(point, float).reshape(-1, 3)
    bary = barycentric(mesh.triangles[face], point)
    normal = interpolated_normals(mesh.vertex_normals, mesh.face_normals, mesh.faces, face, bary)
    return Hits(ray, face, point, bary, normal)


def occluded(rays, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Whether each ray (origins, unit directions (N, 3)) hits the mesh of ``rays`` at all (N,) bool."""
    return np.asarray(rays.intersects_any(origins, directions), bool)
