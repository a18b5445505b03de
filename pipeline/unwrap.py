"""The mesh's UV atlas by xatlas (the maintained unwrapper nvdiffrec uses): charts
packed at a texel size in metres, in pipeline.core.atlas's conventions.

xatlas runs in a child process (``python -m pipeline.unwrap JOB``): on some meshes it crashes the
process it runs in (a segmentation fault on an 81 920-face icosphere, and users' reports on large
scans: jpcy/xatlas#151), which would take the whole fit with it; a crash there is an UnwrapFailed
here.  A fresh interpreter, not multiprocessing: that would import the caller's __main__ again."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from pipeline.core.atlas import MAX_SIZE, Atlas


class UnwrapFailed(RuntimeError):
    """xatlas died unwrapping the mesh (its process crashed)."""


def unwrap(vertices: np.ndarray, faces: np.ndarray, texel_m: float, padding: int = 2) -> Atlas:
    """An atlas of the mesh by xatlas (charts packed at ``texel_m`` metres per texel, ``padding``
    texels between charts so bilinear lookups do not mix them); the size is clamped to MAX_SIZE
    texels a side (the texel then larger than asked: see Atlas.texel_m).  Raises UnwrapFailed when
    xatlas crashes (module docstring)."""
    vertices, faces = np.asarray(vertices, np.float32), np.asarray(faces, np.uint32)
    return in_child(xatlas_atlas, vertices, faces, float(texel_m), int(padding))


def in_child(work, vertices: np.ndarray, faces: np.ndarray, *args):
    """``work(vertices, faces, *args)`` in a child Python process (``work`` a module-level function,
    importable on this process's sys.path) -> its result, or the exception it raised; UnwrapFailed
    where the child dies (a signal, or no result)."""
    with tempfile.TemporaryDirectory(prefix="sigrend-unwrap-") as tmp:
        job = Path(tmp) / "job.pkl"
        job.write_bytes(pickle.dumps((work, vertices, faces, args)))
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        done = subprocess.run([sys.executable, "-m", "pipeline.unwrap", str(job)], env=env)
        answer = job.with_name("answer.pkl")
        if done.returncode != 0 or not answer.exists():
            raise UnwrapFailed(f"xatlas crashed unwrapping the mesh ({len(faces)} faces)")
        ok, value = pickle.loads(answer.read_bytes())
    if not ok:
        raise value
    return value


def xatlas_atlas(vertices: np.ndarray, faces: np.ndarray, texel_m: float, padding: int) -> Atlas:
    """unwrap's work, in the process that calls it (float32 vertices (V, 3), uint32 faces (F, 3))."""
    import xatlas  # lazily: keeps `sigrend --help` fast

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


if __name__ == "__main__":  # in_child's child: JOB -> answer.pkl beside it, (True, result) or (False, exception)
    job = Path(sys.argv[1])
    work, vertices, faces, args = pickle.loads(job.read_bytes())
    try:
        answer = (True, work(vertices, faces, *args))
    except Exception as error:  # handed back to the parent, which raises it
        answer = (False, error)
    job.with_name("answer.pkl").write_bytes(pickle.dumps(answer))
