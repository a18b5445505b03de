"""A simplified proxy of a mesh much finer than the photos resolve (issue 47 item 1), for the
renderer's vertex-level parts: the interreflection (bounce rays, bounce matrices, the vertices'
direct transfer and irradiance) is computed on the proxy's vertices and interpolated to the full
mesh's points; first hits, silhouettes, the samples' visibility and the specular lobes stay on the
full mesh (pipeline.core.render.Renderer takes the proxy from ``RayMesh.proxy``).

The approximation: the light bounced between parts of the object is that of the surface simplified
to an edge length of PROXY_PIXELS photo pixels (the photos' median footprint on the surface,
pipeline.core.atlas.photo_footprint_m), the full mesh's vertex v taking the proxy's value at the
proxy's closest point to v (barycentric in the proxy's face).  Interreflection is a diffuse,
low-frequency part of the radiance (its SH bands <= 4, interreflection.INDIRECT_ORDER), so detail finer than a
few pixels changes it little; docs/fit.md (Speed) has the measured error.  Meshes with fewer than
PROXY_MIN_RATIO times the proxy's faces get no proxy: their numbers are exactly as without it.

The simplification is Fast-Quadric-Mesh-Simplification (the ``fast-simplification`` package).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.atlas import photo_footprint_m
from pipeline.core.surface import barycentric
from pipeline.raycast import RayMesh, ray_mesh

PROXY_PIXELS = 2.0  # the proxy's edge length in photo pixels (4: the Cycles bunny relit 1.62 -> 2.25 %; 2: 1.60 %)
PROXY_MIN_RATIO = 2.0  # a proxy only for a mesh with more than this many times the proxy's faces
CANDIDATE_FACES = 8  # proxy faces (nearest centroids) searched for each vertex's closest point


@dataclass(frozen=True)
class Proxy:
    """The simplified mesh ``mesh`` (a RayMesh: its own intersector) and, per vertex of the full mesh,
    the proxy face's vertex ids ``tri`` (V, 3) and the barycentrics ``bary`` (V, 3) of the proxy's
    point closest to it; ``spacing`` the target edge length (metres)."""

    mesh: RayMesh
    tri: np.ndarray
    bary: np.ndarray
    spacing: float


def proxy_faces(area: float, spacing: float) -> int:
    """Faces of a mesh of ``area`` (m²) tiled by equilateral triangles of edge ``spacing`` (m)."""
    return int(np.ceil(area / (np.sqrt(3.0) / 4.0 * spacing * spacing)))


def with_proxy(mesh, footprint_m: float, pixels: float = PROXY_PIXELS, min_ratio: float = PROXY_MIN_RATIO) -> RayMesh:
    """The RayMesh of ``mesh`` with a Proxy where the mesh is much finer than the photos resolve:
    edge ``pixels`` x ``footprint_m`` (the photos' median pixel size on the surface), and only when
    the mesh has more than ``min_ratio`` times the proxy's faces (else the RayMesh as it is)."""
    rm = ray_mesh(mesh)
    if not (footprint_m > 0 and pixels > 0):
        return rm
    spacing = pixels * footprint_m
    target = proxy_faces(float(rm.mesh.area), spacing)
    if len(rm.faces) <= min_ratio * target:
        return rm
    return replace(rm, proxy=build_proxy(rm, target, spacing))


def build_proxy(rm: RayMesh, target_faces: int, spacing: float = 0.0) -> Proxy:
    """The Proxy of ``rm`` simplified to about ``target_faces`` faces (at least 4)."""
    import fast_simplification
    import trimesh

    points, faces = fast_simplification.simplify(
        np.asarray(rm.vertices, np.float64), np.asarray(rm.faces, np.int32), target_count=max(4, int(target_faces))
    )
    simple = trimesh.Trimesh(points, faces, process=True)  # merged duplicates, dropped degenerate faces
    proxy = ray_mesh(simple)
    tri, bary = closest_points(proxy, rm.vertices, rm.vertex_normals)
    return Proxy(proxy, tri, bary, float(spacing))


def closest_points(proxy: RayMesh, points: np.ndarray, normals: np.ndarray, chunk: int = 65536) -> tuple:
    """(the proxy face's vertex ids (P, 3), barycentrics (P, 3)) of the point of ``proxy`` closest to
    each of ``points`` (P, 3) among the CANDIDATE_FACES faces of nearest centroids, faces facing
    against the point's normal (the other side of a thin part) taken only when no other is near."""
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    tris = np.asarray(proxy.triangles, float)
    tree = cKDTree(tris.mean(axis=1))
    k = min(CANDIDATE_FACES, len(tris))
    out_face = np.zeros(len(points), np.int64)
    out_pt = np.zeros((len(points), 3))
    for s in range(0, len(points), chunk):
        p, n = np.asarray(points[s : s + chunk], float), np.asarray(normals[s : s + chunk], float)
        _, cand = tree.query(p, k=k)
        cand = cand.reshape(len(p), k)
        near = closest_point(tris[cand.ravel()], np.repeat(p, k, axis=0)).reshape(len(p), k, 3)
        dist = np.linalg.norm(near - p[:, None], axis=2)
        facing = np.einsum("pkc,pc->pk", np.asarray(proxy.face_normals)[cand], n) > 0
        dist = np.where(facing | ~facing.any(axis=1, keepdims=True), dist, dist + np.inf)
        best = np.argmin(dist, axis=1)
        out_face[s : s + chunk] = cand[np.arange(len(p)), best]
        out_pt[s : s + chunk] = near[np.arange(len(p)), best]
    bary = np.clip(barycentric(tris[out_face], out_pt), 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    return np.asarray(proxy.faces)[out_face].astype(np.int64), bary


def samples_footprint_m(triangles: np.ndarray, data: dict, poses, keys: list[str]) -> float:
    """The photos' median pixel size on the surface (metres, pipeline.core.atlas.photo_footprint_m) at
    samples ``data`` (face, bary, image_id; samples.npz's) seen through ``poses`` (pipeline.io.poses
    .Poses) of images ``keys`` (image_id's names); ``triangles`` (F, 3, 3) the mesh's."""

    centres = np.array([poses.images[k].cam_from_world.center() for k in keys])
    focal = np.array([poses.camera_of(k).focal_principal()[0] for k in keys])
    ids = np.asarray(data["image_id"], np.int64)
    points = np.einsum("pk,pkc->pc", np.asarray(data["bary"], float), np.asarray(triangles)[data["face"]])
    return photo_footprint_m(points, centres[ids], focal[ids])
