"""The capture's mesh file (DESIGN.md: CAPTURE/mesh.{ply,obj,glb}, object frame, metres) via trimesh."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.workdir import atomic_path

MESH_NAMES = ("mesh.ply", "mesh.obj", "mesh.glb")


def mesh_path(capture: str | os.PathLike) -> Path:
    """The capture's mesh file (one of mesh.ply, mesh.obj, mesh.glb); UserError if there is none
    or more than one (which one is the object would be a guess)."""
    found = [Path(capture) / name for name in MESH_NAMES if (Path(capture) / name).exists()]
    if len(found) > 1:
        raise UserError(
            f"{capture}: {' and '.join(p.name for p in found)} are both there; keep the object's mesh "
            "and move the other out of the capture folder"
        )
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


def write_vertex_albedo(path: str | os.PathLike, mesh, albedo: np.ndarray) -> Path:
    """The mesh with per-vertex linear albedo / base colour (V, 3) as PLY vertex colours x 255
    (uint8; values outside [0, 1] clipped): fit/albedo.ply and synth's gt/albedo.ply, which
    read_vertex_albedo reads."""

    path = Path(path)
    out = mesh.copy()
    out.visual.vertex_colors = np.round(np.clip(albedo, 0.0, 1.0) * 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        out.export(tmp, file_type="ply")
    return path


MATERIAL_PROPERTIES = ("base_r", "base_g", "base_b", "roughness", "metallic", "material_id")


def write_material_ply(path: str | os.PathLike, mesh, values: dict[str, np.ndarray]) -> Path:
    """fit/material.ply (DESIGN.md, "Materials that vary over the surface"): the mesh with float
    vertex properties MATERIAL_PROPERTIES and their standard deviations (``<name>_std``; inf where
    the photos do not determine a value), each (V,) in ``values``; read back by read_material_ply."""
    from trimesh.exchange.ply import export_ply

    missing = [n for n in MATERIAL_PROPERTIES if n not in values]
    if missing:
        raise ValueError(f"material.ply needs {missing}")
    out = mesh.copy()
    out.visual = type(out.visual)()  # the properties are the material; no colours beside them
    for name, column in values.items():
        out.vertex_attributes[name] = np.asarray(column, np.float32)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(export_ply(out, include_attributes=True))
    return path


def read_material_ply(path: str | os.PathLike, n_vertices: int) -> dict[str, np.ndarray] | None:
    """The per-vertex material properties of a material.ply ({name: (V,) float}); None when the file
    is missing or belongs to another mesh (vertex count not ``n_vertices``)."""
    import trimesh

    path = Path(path)
    if not path.exists():
        return None
    try:
        ply = trimesh.load(path, force="mesh", process=False)
        data = ply.metadata["_ply_raw"]["vertex"]["data"]
    except Exception as exc:
        raise UserError(f"{path}: cannot read the material map ({exc}); run `sigrend fit --force` again") from None
    if len(ply.vertices) != n_vertices:
        return None
    names = [n for n in data.dtype.names if n not in ("x", "y", "z")]
    if any(n not in names for n in MATERIAL_PROPERTIES):
        raise UserError(f"{path}: a material map needs the vertex properties {', '.join(MATERIAL_PROPERTIES)}")
    return {n: np.asarray(data[n], float).ravel() for n in names}


def mesh_quality(mesh) -> dict:
    """Counts of what makes a scan a poor model of a surface (trimesh's edge and face structure):
    boundary edges (holes: edges with one face), non-manifold edges (more than two faces),
    degenerate faces (zero area), faces wound against their neighbours (across manifold edges),
    and ``inside_out`` (a closed mesh of negative volume: every normal points in).  Vertices at
    the same position are merged first: a seam of split normals or UVs is not a hole."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=False)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    _, per_edge = np.unique(mesh.edges_sorted, axis=0, return_counts=True)  # faces per edge
    area = mesh.area_faces
    degenerate = int(np.sum(area <= 1e-12 * max(float(area.max(initial=0.0)), 1e-300)))
    # a manifold edge is consistently wound when its two faces traverse it in opposite directions
    adjacency, shared = mesh.face_adjacency, mesh.face_adjacency_edges

    def traverses(face_ids):
        f = mesh.faces[face_ids]
        a, b = shared[:, 0:1], shared[:, 1:2]
        nxt = np.roll(f, -1, axis=1)
        return np.any((f == a) & (nxt == b), axis=1)

    flipped_pairs = traverses(adjacency[:, 0]) == traverses(adjacency[:, 1])
    watertight = bool(len(per_edge) and np.all(per_edge == 2))
    inside_out = bool(watertight and not flipped_pairs.any() and mesh.volume < 0)
    return {
        "faces": int(len(mesh.faces)),
        "boundary_edges": int(np.sum(per_edge == 1)),
        "non_manifold_edges": int(np.sum(per_edge > 2)),
        "degenerate_faces": degenerate,
        "inconsistent_edges": int(flipped_pairs.sum()),
        "inside_out": inside_out,
    }


def check_mesh_quality(path: str | os.PathLike, mesh) -> tuple[dict, list[str]]:
    """mesh_quality of the capture's mesh, and warnings for what it found; UserError where the
    samples would be wrong: faces wound against their neighbours (their normals point the other
    way, so their pixels shade as the inside) and a closed mesh turned inside out."""
    quality = mesh_quality(mesh)
    fix = "fix the winding (Blender: Mesh > Normals > Recalculate Outside; trimesh.repair.fix_normals) and run again"
    if quality["inside_out"]:
        raise UserError(f"{path}: the mesh is inside out (closed, negative volume: every normal points inwards); {fix}")
    if quality["inconsistent_edges"]:
        raise UserError(
            f"{path}: {quality['inconsistent_edges']} edges join faces wound in opposite directions "
            f"(flipped faces: their normals point inwards); {fix}"
        )
    warnings = []
    if quality["boundary_edges"]:
        warnings.append(
            f"{quality['boundary_edges']} boundary edges (holes, an open scan): shadow and view rays "
            "pass through them, so where the real object is closed its shadows and interreflection "
            "there are missing"
        )
    if quality["non_manifold_edges"]:
        warnings.append(f"{quality['non_manifold_edges']} non-manifold edges (shared by more than two faces)")
    if quality["degenerate_faces"]:
        warnings.append(f"{quality['degenerate_faces']} degenerate (zero-area) faces")
    return quality, [f"{path}: {w}" for w in warnings]
