"""fit/textures/: the spatially varying base colour on a UV atlas (DESIGN.md, "fit/textures/").

atlas.npz           face_uv (F, 3, 2) float32: each face corner's UV, glTF's convention
                    (pipeline.core.atlas); height, width (texels); texel_mm (0: the mesh's own UVs)
base_color.exr      linear base colour (H, W, 3) float32, padded past the charts — the one relight reads
base_color.png      the same in 8-bit sRGB, for glTF's baseColorTexture and image viewers
base_color_std.exr  per-texel standard deviation of the base colour (H, W, 3); NaN where no sample fell
with a material map (fit/material.ply) also:
roughness.exr, metallic.exr   (H, W) float32, linear: each texel's material's (perceptual roughness)
metallic_roughness.png        the two packed as glTF's metallicRoughnessTexture: linear 8-bit,
                              G = roughness, B = metallic, R = 1 (unoccluded, were it read as ORM)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.atlas import Atlas
from pipeline.io.images import read_image, srgb_encode, write_image
from pipeline.workdir import atomic_path

FOLDER = "textures"
NAMES = ("atlas.npz", "base_color.exr", "base_color.png", "base_color_std.exr")
MATERIAL_NAMES = ("roughness.exr", "metallic.exr", "metallic_roughness.png")


def write_base_color_textures(
    folder: str | os.PathLike,
    atlas: Atlas,
    base: np.ndarray,
    std: np.ndarray,
    roughness: np.ndarray | None = None,
    metallic: np.ndarray | None = None,
) -> list[Path]:
    """The files of the module docstring into ``folder`` (fit/textures/), the roughness and metallic
    ones when both maps (H, W) are given (else a stale set is removed). -> their paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "atlas.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, face_uv=atlas.face_uv.astype(np.float32), height=atlas.height, width=atlas.width, texel_mm=1e3 * atlas.texel_m
            )
    written = [
        folder / "atlas.npz",
        write_image(folder / "base_color.exr", base.astype(np.float32), dtype="float"),
        write_image(folder / "base_color.png", srgb_encode(base), dtype="uint8"),
        write_image(folder / "base_color_std.exr", std.astype(np.float32), dtype="half"),
    ]
    if roughness is None or metallic is None:
        for name in MATERIAL_NAMES:
            (folder / name).unlink(missing_ok=True)  # export would pack a stale map with this fit's base colour
        return written
    packed = np.stack([np.ones_like(roughness), roughness, metallic], axis=-1)
    return written + [
        write_image(folder / "roughness.exr", roughness.astype(np.float32), dtype="float"),
        write_image(folder / "metallic.exr", metallic.astype(np.float32), dtype="float"),
        write_image(folder / "metallic_roughness.png", np.clip(packed, 0.0, 1.0), dtype="uint8"),
    ]


def read_base_color_texture(folder: str | os.PathLike, n_faces: int) -> tuple[Atlas, np.ndarray] | None:
    """(the atlas, the linear base colour map (H, W, 3)) of fit/textures/, or None when it is absent
    or made for another mesh (its face count is not ``n_faces``)."""
    folder = Path(folder)
    if not (folder / "atlas.npz").exists() or not (folder / "base_color.exr").exists():
        return None
    with np.load(folder / "atlas.npz") as doc:
        face_uv = doc["face_uv"].astype(float)
        atlas = Atlas(face_uv, int(doc["height"]), int(doc["width"]), float(doc["texel_mm"]) / 1e3)
    if len(face_uv) != n_faces:
        return None
    return atlas, read_image(folder / "base_color.exr")[:, :, :3].astype(float)
