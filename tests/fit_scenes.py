"""Synthetic scenes for the fit tests: an analytic environment, sphere samples seen from several
views (as a samples file, or as the physical fit's prt.Geometry: sphere_geometry), and radiance
by direct numerical integration of the reflection equation over the environment's pixels
(independent of the SH forward model the fit inverts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from pipeline.core import prt
from pipeline.core.brdf import Brdf, cosine_weighted_brdf
from pipeline.core.envmap import equirect_directions, equirect_solid_angles
from pipeline.io.samples import write_samples
from pipeline.raycast import ray_mesh


def sharp_env(height: int = 48, sun_width: float = 0.01, sun_power: float = 20.0) -> np.ndarray:
    """Sky gradient plus two bright lights (exp((cos - 1) / width) blobs): (H, 2H, 3)."""
    d = equirect_directions(height)
    env = 0.3 + 0.2 * d[..., 2:3] * np.array([0.8, 1.0, 1.2])
    for axis, colour in (([0.5, 0.3, 0.8], [1.0, 0.9, 0.7]), ([-0.6, 0.2, 0.3], [0.4, 0.5, 0.8])):
        a = np.asarray(axis) / np.linalg.norm(axis)
        env = env + sun_power * np.exp((d @ a - 1.0) / sun_width)[..., None] * np.asarray(colour)
    return env


def smooth_env(height: int = 48) -> np.ndarray:
    """Soft lighting: only bands 0-2 (a constant plus a dipole and a quadrupole, all positive)."""
    d = equirect_directions(height)
    x, y, z = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    return 1.0 + 0.4 * z * np.array([1.0, 0.9, 0.8]) + 0.2 * (x * y) + 0.15 * (3 * z * z - 1) * np.array([0.7, 1.0, 1.0])


def sphere_views(rng: np.random.Generator, views: int, per_view: int, min_cos: float = 0.2):
    """Normals of a unit sphere seen by distant cameras in random directions: (normal, view_dir, image_id)."""
    cams = rng.normal(size=(views, 3))
    cams /= np.linalg.norm(cams, axis=1, keepdims=True)
    normals, dirs, ids = [], [], []
    for i, c in enumerate(cams):
        n = rng.normal(size=(per_view * 4, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n = n[n @ c > min_cos][:per_view]
        normals.append(n)
        dirs.append(np.broadcast_to(c, n.shape))
        ids.append(np.full(len(n), i))
    return np.concatenate(normals), np.concatenate(dirs), np.concatenate(ids)


def integrate_radiance(env: np.ndarray, brdf: Brdf, normal: np.ndarray, view_dir: np.ndarray, chunk: int = 256) -> np.ndarray:
    """B = sum over env pixels of L(w) f(w, v) max(0, n.w) Omega_pixel (midpoint rule), (N, 3)."""
    h = env.shape[0]
    dirs = equirect_directions(h).reshape(-1, 3)
    omega = np.repeat(equirect_solid_angles(h), 2 * h)
    radiance = env.reshape(-1, 3) * omega[:, None]
    out = np.empty((len(normal), 3))
    p = len(dirs)
    for s in range(0, len(normal), chunk):
        n = normal[s : s + chunk]
        v = view_dir[s : s + chunk]
        m = len(n)
        t = cosine_weighted_brdf(brdf, np.repeat(n, p, axis=0), np.tile(dirs, (m, 1)), np.repeat(v, p, axis=0))
        out[s : s + chunk] = np.einsum("mpc,pc->mc", t.reshape(m, p, 3), radiance)
    return out


def write_scene(work: Path, normal, view_dir, image_id, radiance, visibility=None) -> Path:
    """WORK/samples.npz in the samples schema (pipeline.io.samples) from arrays."""
    n = len(normal)
    arrays = {
        "point": normal,
        "normal": normal,
        "view_dir": view_dir,
        "radiance": radiance,
        "image_id": image_id,
        "pixel": np.zeros((n, 2)),
        "face": np.zeros(n),
        "bary": np.zeros((n, 3)),
        "weight": np.ones(n),
        "visibility": np.ones(n) if visibility is None else visibility,
        "image_keys": [f"{i:04d}.exr" for i in range(int(image_id.max()) + 1)],
    }
    return write_samples(Path(work) / "samples.npz", arrays, {"source": "tests/fit_scenes.py"})


def sphere_geometry(rng, n: int = 3000, order: int = 3) -> prt.Geometry:
    """Samples on a unit icosphere seen from random directions in their front hemisphere."""
    mesh = trimesh.creation.icosphere(subdivisions=4)
    faces = rng.integers(0, len(mesh.faces), n)
    bary = rng.dirichlet([1.0, 1.0, 1.0], n)
    normals = np.asarray(mesh.face_normals)[faces]
    view = normals + rng.normal(0.0, 0.6, (n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    view[np.einsum("pk,pk->p", view, normals) < 0.05] = normals[np.einsum("pk,pk->p", view, normals) < 0.05]
    return prt.geometry(ray_mesh(mesh), faces, bary, view, order)
