"""The mesh's UV atlas by xatlas (the maintained unwrapper nvdiffrec uses): charts
packed at a texel size in metres, in pipeline.core.atlas's conventions."""

from __future__ import annotations

import numpy as np

from pipeline.core.atlas import MAX_SIZE, Atlas


def unwrap(vertices: np.ndarray, faces: np.ndarray, texel_m: float, padding: int = 2) -> Atlas:
    """An atlas of the mesh by xatlas (charts packed at ``texel_m`` metres per texel, ``padding``
    texels between charts so bilinear lookups do not mix them); the size is clamped to MAX_SIZE
    texels a side (the texel then larger than asked: see Atlas.texel_m)."""
    import xatlas  # lazily: keeps `sigrend --help` fast

    vertices, faces = np.asarray(vertices, np.float32), np.asarray(faces, np.uint32)
    area = float(
        np.linalg.norm(
            np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1
        ).sum()
        / 2
    )
    texel_m = max(float(texel_m), np.sqrt(area / (0.5 * MAX_SIZE**2)))  # ~50 % packing efficiency
    atlas = xatlas.Atlas()
    # in texel units: xatlas gives no UV area to a face whose area is below FLT_EPSILON in its units (in
    # metres every face under 0.12 mm^2: 37 % of a 30k-face scan of a walnut, its texture then blotched)
    atlas.add_mesh(vertices / np.float32(texel_m), faces)
    pack = xatlas.PackOptions()
    pack.texels_per_unit = 1.0
    pack.padding = int(padding)
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    vmapping, indices, uvs = atlas[0]
    if not np.array_equal(vmapping[indices], faces):  # xatlas keeps the faces' order and corners
        raise RuntimeError("xatlas reordered the mesh's faces")
    return Atlas(np.asarray(uvs, float)[indices], int(atlas.height), int(atlas.width), texel_m)
