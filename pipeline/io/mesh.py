"""The capture's mesh file (DESIGN.md: CAPTURE/mesh.{ply,obj,glb}, object frame, metres) via trimesh."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import UserError

MESH_NAMES = ("mesh.ply", "mesh.obj", "mesh.glb")


def mesh_path(capture: str | os.PathLike) -> Path:
    """The capture's mesh file (one of mesh.ply, mesh.obj, mesh.glb); UserError if there is none
    or more than one (which one is the object would be a guess)."""
    found = [Path(capture) / name for name in MESH_NAMES if (Path(capture) / name).exists()]
    if len(found) > 1:
        raise UserError(f"{capture}: {' and '.join(p.name for p in found)} are both there; keep the object's mesh "
                        "and move the other out of the capture folder")
    if not found:
        raise UserError(f"{capture}: no mesh found; put the object's mesh in the capture as {' or '.join(MESH_NAMES)}")
    return found[0]


def read_mesh(path: str | os.PathLike):
    """One trimesh.Trimesh (a scene's geometries concatenated, vertices merged); UserError if the
    file is missing, unreadable or has no triangles."""
    import trimesh  # lazily: keeps `sigrend --help` fast

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise UserError(f"{path}: cannot read the mesh ({exc}); export it again as PLY or OBJ") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"{path}: the mesh has no triangles; a triangle mesh is needed")
    return mesh


def read_vertex_albedo(path: str | os.PathLike, n_vertices: int) -> np.ndarray | None:
    """Per-vertex linear albedo / base colour (V, 3) in [0, 1] from a PLY with vertex colours
    (fit/albedo.ply, gt/albedo.ply: linear values x 255); None when the file is missing or its
    vertex count is not ``n_vertices`` (another mesh's)."""
    import trimesh

    path = Path(path)
    if not path.exists():
        return None
    try:
        tex = trimesh.load(path, force="mesh", process=False)  # as written: merging would renumber the vertices
    except Exception as exc:
        raise UserError(f"{path}: cannot read the per-vertex albedo ({exc}); run `sigrend fit --force` again") from None
    colors = getattr(tex.visual, "vertex_colors", None)
    if colors is None or len(tex.vertices) != n_vertices:
        return None
    colors = np.asarray(colors, float)[:, :3]
    return colors / 255.0 if colors.max() > 1.0 else colors
