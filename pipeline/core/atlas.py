"""A texture atlas on the mesh, for the spatially varying material's maps.

Conventions (glTF 2.0's, so the exporter writes the UVs as they are): each face corner has a UV in
[0, 1]^2, (0, 0) the image's top-left corner, u to the right, v down; texel (row, col) of an
H x W map covers [col, col + 1] / W x [row, row + 1] / H, so its centre is at
u = (col + 0.5) / W, v = (row + 0.5) / H.  A map is an (H, W, C) array, row 0 at the top.

The atlas is the mesh's own UVs when it has them, else an unwrap by xatlas (pipeline.unwrap) at a
texel size given in metres (the photos' footprint on the surface, :func:`photo_footprint_m`).  Pure
NumPy/SciPy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

MAX_SIZE = 4096  # texels per side at most: a finer footprint is clamped (and said in the report)


@dataclass(frozen=True)
class Atlas:
    """UVs per face corner ``face_uv`` (F, 3, 2) and the maps' size ``height`` x ``width`` texels;
    ``texel_m``: the texel size the atlas was made for (metres; 0 for a mesh's own UVs)."""

    face_uv: np.ndarray
    height: int
    width: int
    texel_m: float = 0.0

    def uv_at(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """UV (P, 2) of points given by face ids (P,) and barycentrics (P, 3)."""
        return np.einsum("pk,pkc->pc", np.asarray(bary, float), self.face_uv[np.asarray(faces, np.int64)])

    def texel_of(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Flat index row * width + col (P,) of the texel each point falls in."""
        uv = self.uv_at(faces, bary)
        col = np.clip((uv[:, 0] * self.width).astype(np.int64), 0, self.width - 1)
        row = np.clip((uv[:, 1] * self.height).astype(np.int64), 0, self.height - 1)
        return row * self.width + col

    def lookup(self, image: np.ndarray, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Bilinear value (P, C) of the map ``image`` (H, W, C) at points (edge texels repeated)."""
        uv = self.uv_at(faces, bary)
        coords = [uv[:, 1] * self.height - 0.5, uv[:, 0] * self.width - 0.5]  # texel centres at +0.5
        image = np.asarray(image, float)
        return np.stack(
            [ndimage.map_coordinates(image[:, :, c], coords, order=1, mode="nearest") for c in range(image.shape[2])], axis=1
        )

    def at_vertices(self, image: np.ndarray, faces: np.ndarray, n_vertices: int) -> np.ndarray:
        """The map at the mesh's vertices (V, C): the mean over each vertex's face corners (a vertex on
        a seam has one UV per chart)."""
        faces = np.asarray(faces, np.int64)
        f = np.repeat(np.arange(len(faces)), 3)
        bary = np.tile(np.eye(3), (len(faces), 1))
        values = self.lookup(image, f, bary)
        count = np.bincount(faces.ravel(), minlength=n_vertices).astype(float)
        out = np.stack([np.bincount(faces.ravel(), values[:, c], minlength=n_vertices) for c in range(values.shape[1])], axis=1)
        return out / np.maximum(count, 1.0)[:, None]


def photo_footprint_m(points: np.ndarray, centres: np.ndarray, focal_px: np.ndarray) -> float:
    """The median size (metres) of one pixel on the surface: distance from the camera / focal length
    (px), over samples at ``points`` (N, 3) seen from camera centres ``centres`` (N, 3) with focal
    lengths ``focal_px`` (N,)."""
    distance = np.linalg.norm(np.asarray(points, float) - np.asarray(centres, float), axis=1)
    return float(np.median(distance / np.asarray(focal_px, float)))


def from_vertex_uv(uv: np.ndarray, faces: np.ndarray, size: int) -> Atlas:
    """The mesh's own per-vertex UVs (V, 2) in OBJ/trimesh convention (v up) as an atlas of
    ``size`` x ``size`` texels."""
    uv = np.asarray(uv, float)
    flipped = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)
    return Atlas(flipped[np.asarray(faces, np.int64)], int(size), int(size))


def texel_points(atlas: Atlas, chunk: int = 1 << 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surface point under each covered texel centre: (flat texel index (M,), face (M,),
    barycentrics (M, 3)), a texel taken by the first face whose UV triangle holds its centre
    (charts do not overlap; ``chunk`` candidate texel-face pairs at a time)."""
    size = np.array([atlas.width, atlas.height], float)
    corners = atlas.face_uv * size - 0.5  # in texel-centre coordinates
    lo = np.maximum(np.floor(corners.min(axis=1)).astype(np.int64), 0)
    hi = np.minimum(np.ceil(corners.max(axis=1)).astype(np.int64), [atlas.width - 1, atlas.height - 1])
    span = np.maximum(hi - lo + 1, 0)
    count = span[:, 0] * span[:, 1]
    found_texel, found_face, found_bary = [], [], []
    starts = np.concatenate([[0], np.cumsum(count)])
    first = 0
    while first < len(count):
        last = int(np.searchsorted(starts, starts[first] + chunk, side="right")) - 1
        last = max(last, first + 1)
        faces = np.repeat(np.arange(first, last), count[first:last])
        k = np.arange(len(faces)) - np.repeat(starts[first:last] - starts[first], count[first:last])
        col = lo[faces, 0] + k % span[faces, 0]
        row = lo[faces, 1] + k // span[faces, 0]
        a, b, c = corners[faces, 0], corners[faces, 1], corners[faces, 2]
        p = np.stack([col, row], axis=1).astype(float)
        v0, v1, v2 = b - a, c - a, p - a
        det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            w1 = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
            w2 = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
        w0 = 1.0 - w1 - w2
        inside = (np.abs(det) > 0) & (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        found_texel.append(row[inside] * atlas.width + col[inside])
        found_face.append(faces[inside])
        found_bary.append(np.stack([w0, w1, w2], axis=1)[inside])
        first = last
    texel = np.concatenate(found_texel)
    texel, keep = np.unique(texel, return_index=True)
    return texel, np.concatenate(found_face)[keep], np.clip(np.concatenate(found_bary)[keep], 0.0, 1.0)


def paint(atlas: Atlas, texel: np.ndarray, values: np.ndarray, pad: int = 8, fill: float = 0.0) -> np.ndarray:
    """An (H, W, C) map holding ``values`` (M, C) at the flat texels ``texel`` (M,) (texel_points'),
    padded ``pad`` rings past them (:func:`dilate`); texels further out are ``fill``."""
    values = np.asarray(values, float).reshape(len(texel), -1)
    flat = np.full((atlas.height * atlas.width, values.shape[1]), float(fill))
    flat[texel] = values
    filled = np.zeros(atlas.height * atlas.width, bool)
    filled[texel] = True
    shape = (atlas.height, atlas.width)
    return dilate(flat.reshape(*shape, -1), filled.reshape(shape), pad)


def dilate(image: np.ndarray, filled: np.ndarray, texels: int = 8) -> np.ndarray:
    """``image`` (H, W, C) with the texels outside ``filled`` (H, W) given their filled neighbours'
    mean, ``texels`` rings outwards: the padding that keeps a renderer's bilinear and mip-mapped
    lookups at chart edges from mixing in the empty background."""
    out = np.array(image, float)
    have = np.asarray(filled, bool).copy()
    kernel = np.ones((3, 3))
    for _ in range(int(texels)):
        if have.all():
            break
        weight = ndimage.convolve(have.astype(float), kernel, mode="constant")
        ring = (~have) & (weight > 0)
        for c in range(out.shape[2]):
            total = ndimage.convolve(np.where(have, out[:, :, c], 0.0), kernel, mode="constant")
            out[:, :, c][ring] = total[ring] / weight[ring]
        have |= ring
    return out
