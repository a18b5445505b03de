"""The fit's samples: read from samples.npz in chunks, filtered (zero weight, non-finite,
self-shadowed for the convex model, off the mesh for the physical one) and subsampled with the
stage's seed.  Arrays are float64 except the integer fields (image_id, face, pixel).  The physical
transfer's normals and view directions over each sample's pixel: sample_footprints."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.noise import inverse_variance_weights, noise_level_function, pixel_noise_sigma, weighted_noise_sigma
from pipeline.errors import UserError
from pipeline.io.poses import poses_path, read_poses
from pipeline.io.samples import iter_sample_chunks, read_samples_meta
from pipeline.memory import Budget
from pipeline.raycast import RayMesh, pixel_footprints
from stages.fit.settings import Settings

# the fit's peak memory per sample of its every-sample steps, with room: the texels step on a real walnut's
# 1280x1024 ring measured ~430 (peak 2.27 GB without it, 2.63 / 3.08 GB with 1.33 / 2.66 M samples);
# the material map shades three candidates at each
EVERY_SAMPLE_BYTES = 700
EVERY_SAMPLE_SHARE = 0.5  # of --memory-limit: the rest for the mesh's transfer, the subset's fits and the imports
FIELDS = ("normal", "view_dir", "radiance", "image_id", "weight", "visibility")  # the convex model's
PHYSICAL_FIELDS = ("face", "bary", "view_dir", "radiance", "image_id", "weight", "normal", "pixel")


def filter_rows(chunk: dict, settings: Settings, min_cos: float) -> np.ndarray:
    """Rows of a chunk the convex fit uses: positive weight, visibility >= min_visibility, finite
    radiance (and n.v >= ``min_cos``)."""
    ok = (chunk["weight"] > 0) & (chunk["visibility"] >= settings.min_visibility)
    if min_cos > 0:
        ok &= np.einsum("ij,ij->i", chunk["normal"], chunk["view_dir"]) >= min_cos
    return ok & np.all(np.isfinite(chunk["radiance"]), axis=1)


def iter_valid_chunks(path: Path, settings: Settings, min_cos: float = 0.0):
    """Chunks of the samples (float64), leaving out self-shadowed, zero-weight and non-finite rows
    (and views with n.v < min_cos)."""
    for chunk in iter_sample_chunks(path, settings.chunk, FIELDS):
        ok = filter_rows(chunk, settings, min_cos)
        if ok.any():
            yield {k: (v[ok].astype(np.float64) if v.dtype.kind == "f" else v[ok]) for k, v in chunk.items()}


def load_subset(path: Path, settings: Settings, total: int, min_cos: float) -> dict:
    """At most ``max_samples`` valid samples in memory (uniform random subset)."""
    rng = np.random.default_rng(settings.seed)
    keep_fraction = min(1.0, settings.max_samples / max(total, 1))
    parts = []
    for chunk in iter_valid_chunks(path, settings, min_cos):
        if keep_fraction < 1.0:
            sel = rng.random(len(chunk["weight"])) < keep_fraction
            chunk = {k: v[sel] for k, v in chunk.items()}
        parts.append(chunk)
    if not parts:
        return {}
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def every_sample_cap(path: Path, settings: Settings) -> tuple[float, dict]:
    """The share of samples.npz's rows the fit holds for its every-sample steps (the texels step, the
    material map: EVERY_SAMPLE_BYTES each) within EVERY_SAMPLE_SHARE of --memory-limit -> (the share
    in (0, 1], report.json's "every_sample" note).  UserError where that is fewer than --physical-samples."""
    budget = Budget.of(settings.memory_limit)
    rows = int(read_samples_meta(path).get("count", 0))
    most = int(EVERY_SAMPLE_SHARE * budget.limit // EVERY_SAMPLE_BYTES)
    if most < settings.physical_samples:
        raise budget.too_small(
            int(settings.physical_samples * EVERY_SAMPLE_BYTES / EVERY_SAMPLE_SHARE),
            f"the fit's subset of {settings.physical_samples} samples",
            "lower --physical-samples",
        )
    share = min(1.0, most / max(rows, 1))
    note = {"rows": rows, "share": share, "most": most, "memory_limit": budget.text}
    if share < 1.0:
        note["why"] = (
            f"--memory-limit {budget.text}: the every-sample steps hold at most {most} samples "
            f"({EVERY_SAMPLE_BYTES} bytes each in {EVERY_SAMPLE_SHARE:.0%} of the limit), a random {share:.1%} of {rows}"
        )
    return share, note


def load_physical(path: Path, settings: Settings, n_faces: int, share: float = 1.0) -> tuple[dict, dict, dict]:
    """At most ``physical_samples`` usable samples (positive weight, finite, on the mesh), the photos'
    noise measured on all of them, and all of them (the per-texel fit's: every pixel counts) — or a
    random ``share`` of them (every_sample_cap: what --memory-limit holds).
    The noise (pipeline.core.noise): {"sigma": the pixel noise (NaN if
    unmeasurable), "a", "b": the Poisson-Gaussian noise level sigma^2 = a + b B, "weighting"}.
    With ``--noise-model measured`` each sample's weight is divided by its noise variance
    (normalized at the median radiance), a floored at (noise_floor x RMS radiance)^2: a highlight
    pixel 100x the median is ~100x noisier (shot noise, a path tracer's), and unweighted, a few
    of them at a sphere's rim ruled the roughness (the Cycles night sphere: 0.176 for 0.15)."""
    parts = []
    rng = np.random.default_rng([settings.seed, 1])  # its own stream: the subset below draws from the seed
    for chunk in iter_sample_chunks(path, settings.chunk, PHYSICAL_FIELDS):
        ok = (chunk["weight"] > 0) & np.all(np.isfinite(chunk["radiance"]), axis=1)
        ok &= (chunk["face"] >= 0) & (chunk["face"] < n_faces)
        if share < 1.0:
            ok &= rng.random(len(ok)) < share
        parts.append({k: v[ok] for k, v in chunk.items()})
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
    n = len(data.get("weight", []))
    if n == 0:
        raise UserError(f"{path}: no samples with positive weight on the mesh; check the samples stage's drop counts")
    sigma = pixel_noise_sigma(data["radiance"], data["image_id"], data["pixel"])
    noise = {"sigma": sigma, "unit_sigma": sigma, "weighting": "uniform"}
    if settings.noise_model == "measured":
        a, b = noise_level_function(data["radiance"], data["image_id"], data["pixel"])
        if np.isfinite(a) and np.isfinite(b):
            a = max(a, (settings.noise_floor * float(np.sqrt(np.mean(data["radiance"].astype(float) ** 2)))) ** 2)
            data["weight"] = data["weight"] * inverse_variance_weights(data["radiance"], a, b).astype(np.float32)
            noise.update(
                a=a,
                b=b,
                unit_sigma=weighted_noise_sigma(data["weight"], data["radiance"], a, b),
                weighting="1 / (a + b B), B the sample's channel-mean radiance, normalized at the "
                "median; a floored at (noise_floor x RMS radiance)^2",
            )
        else:
            noise["weighting"] = "uniform (the noise level could not be measured: too few neighbouring samples)"
    everything = data
    if n > settings.physical_samples:
        keep = np.sort(np.random.default_rng(settings.seed).choice(n, settings.physical_samples, replace=False))
        data = {k: v[keep] for k, v in data.items()}
    return data, noise, everything


def sample_footprints(capture: Path, work: Path, mesh: RayMesh, data: dict, keys: list[str], n: int) -> tuple | None:
    """Normals and view directions (N, n*n, 3) over each sample's pixel (pipeline.raycast
    .pixel_footprints on ``mesh``'s intersector, through the poses the samples were made with);
    None for n = 1."""
    if n <= 1:
        return None
    path = poses_path(capture, work)
    poses = read_poses(path)
    rays = mesh.rays
    normals = np.zeros((data["face"].size, n * n, 3))
    views = np.zeros_like(normals)
    for i in np.unique(data["image_id"]):
        key = keys[int(i)]
        if key not in poses.images:
            raise UserError(f"{path} has no pose for {key}, which samples.npz was made from; run `sigrend samples` again")
        sel = np.flatnonzero(data["image_id"] == i)
        pose = poses.images[key]
        normals[sel], views[sel] = pixel_footprints(
            mesh,
            rays,
            poses.camera_of(key),
            pose.cam_from_world.rotation,
            pose.cam_from_world.translation,
            data["pixel"][sel],
            n,
            data["normal"][sel],
            data["view_dir"][sel],
        )
    return normals, views
