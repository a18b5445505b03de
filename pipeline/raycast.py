"""The stages' ray casting against the capture's mesh (trimesh's Embree intersector, embreex):
first hits of camera rays as surface points — face, point, barycentrics, shading normal by
pipeline.core.surface's one rule — occlusion tests, and the surface a pixel sees (its footprint).
Used by the samples stage, the fit and relight; the renderer (pipeline.core.render) casts its
camera, shadow and bounce rays through a RayMesh made here (ray_mesh), so that core imports
neither trimesh nor Embree, and takes its surface points from the same pipeline.core.surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.camera import camera_center, pixel_rays, subpixel_offsets
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


@dataclass(frozen=True)
class RayMesh:
    """A mesh as the renderer (pipeline.core.render.Renderer) takes it: its arrays (vertices (V, 3),
    faces (F, 3), unit vertex and face normals, triangles (F, 3, 3), extents (3,) of its box) and
    its Embree intersector ``rays`` (intersects_id, intersects_any); ``mesh`` is the trimesh mesh;
    ``proxy``: a pipeline.proxy.Proxy (a simplified mesh for the renderer's vertex-level parts) or None."""

    mesh: object
    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    face_normals: np.ndarray
    triangles: np.ndarray
    extents: np.ndarray
    rays: object
    proxy: object = None

    def with_occluder(self, corners: np.ndarray):
        """An intersector of the mesh together with a planar quad (corners (4, 3), in order), e.g.
        the capture's board, which shadows the object."""
        import trimesh

        quad = trimesh.Trimesh(np.asarray(corners, float), [[0, 1, 2], [0, 2, 3]], process=False)
        return intersector(trimesh.util.concatenate([self.mesh, quad]))


def ray_mesh(mesh) -> RayMesh:
    """The RayMesh of a trimesh mesh (its intersector built once, shared by every Renderer of it)."""
    if isinstance(mesh, RayMesh):
        return mesh
    return RayMesh(
        mesh,
        np.asarray(mesh.vertices, float),
        np.asarray(mesh.faces),
        np.asarray(mesh.vertex_normals, float),
        np.asarray(mesh.face_normals, float),
        np.asarray(mesh.triangles, float),
        np.asarray(mesh.extents, float),
        intersector(mesh),
    )


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


def pixel_footprints(
    mesh, rays, camera, R: np.ndarray, t: np.ndarray, pixels: np.ndarray, n: int, normals: np.ndarray, view_dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The surface each pixel integrates: shading normals and unit view directions (P, n*n, 3) at
    the hits of an n x n grid of rays through each pixel (row, col) of ``pixels`` (P, 2) — a
    one-pixel box filter, as a sensor's pixel or a path tracer's box filter averages.  A ray that
    misses the mesh takes the pixel's own ``normals`` / ``view_dirs`` (P, 3) (the centre's)."""
    pixels = np.asarray(pixels)
    k = n * n
    offsets = subpixel_offsets(n)
    ox, oy = (a.ravel() for a in np.meshgrid(offsets, offsets))
    uv = np.stack([(pixels[:, 1, None] + 0.5 + ox).ravel(), (pixels[:, 0, None] + 0.5 + oy).ravel()], axis=1)
    out_n = np.repeat(np.asarray(normals, float)[:, None], k, axis=1).reshape(-1, 3)
    out_v = np.repeat(np.asarray(view_dirs, float)[:, None], k, axis=1).reshape(-1, 3)
    origins, dirs = pixel_rays(camera, R, t, uv)
    h = first_hits(mesh, rays, origins, dirs)
    out_n[h.ray] = h.normal
    view = camera_center(R, t) - h.point
    out_v[h.ray] = view / np.linalg.norm(view, axis=1, keepdims=True)
    return out_n.reshape(-1, k, 3), out_v.reshape(-1, k, 3)
