"""The fit's textured vs uniform diffuse albedo (--albedo): a per-vertex albedo with the fitted
lighting and specular part fixed (pipeline.core.texture), kept only when the held-out views prefer
it, for either forward model; on the physical one with the residual per view of the chosen fit
(texture_and_residuals) and the texture's pattern the material is chosen again with
(texture_pattern).  Where the physical fit's mesh has an interreflection proxy (pipeline.proxy: a
simplified mesh at the photos' resolution) the albedo's unknowns are the proxy's vertices
(texture.CoarseBasis) and the albedo is interpolated to the mesh's vertices with the proxy's
barycentrics for every consumer (albedo.ply, the pattern, relight)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.core import forward, material_fit, prt, texture
from pipeline.core.brdf import Brdf
from pipeline.core.candidate import Observations
from pipeline.core.factorization import rms_radiance
from pipeline.core.selection import fold_of
from pipeline.errors import UserError
from pipeline.io.mesh import mesh_path, read_mesh
from pipeline.io.samples import iter_sample_chunks
from stages.fit.data import FIELDS, filter_rows
from stages.fit.outputs import residuals_per_view
from stages.fit.settings import Settings


def choose_albedo(
    capture: Path, samples_path: Path, settings: Settings, coeffs: np.ndarray, brdf: Brdf
) -> tuple[dict, np.ndarray | None, object]:
    """Fit a per-vertex diffuse albedo with the fitted lighting and specular part fixed, and choose
    textured vs uniform by the held-out views (folds = image_id mod folds): textured only when its
    validation RMSE is below uniform's by more than ``parsimony``.  Returns (report entry,
    per-vertex albedo (V, 3) or None, mesh)."""
    entry: dict = {"setting": settings.albedo, "smoothness": settings.albedo_smoothness}
    if settings.albedo == "uniform":
        return {**entry, "choice": "uniform", "note": "--albedo uniform: no per-vertex fit"}, None, None
    try:
        mesh = read_mesh(mesh_path(capture))
    except UserError as exc:
        if settings.albedo == "textured":
            raise
        return {**entry, "choice": "uniform", "note": f"no per-vertex fit: {exc}"}, None, None
    with_lobe = brdf.has_lobe
    rng = np.random.default_rng(settings.seed)
    parts = []
    for chunk in iter_sample_chunks(samples_path, settings.chunk, FIELDS + ("face", "bary")):
        ok = filter_rows(chunk, settings, settings.lobe_min_cos if with_lobe else 0.0)
        ok &= (chunk["face"] >= 0) & (chunk["face"] < len(mesh.faces))
        parts.append({k: v[ok] for k, v in chunk.items()})
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
    n = len(data.get("weight", []))
    if n > settings.max_samples:
        sel = rng.choice(n, settings.max_samples, replace=False)
        data = {k: v[sel] for k, v in data.items()}
        n = settings.max_samples
    if n == 0 or np.abs(data["bary"].sum(axis=1) - 1).max() > 1e-3:
        if settings.albedo == "textured":
            raise UserError(
                f"{samples_path}: the samples carry no face/barycentrics on the mesh; "
                "--albedo textured needs them (run the samples stage)"
            )
        return {**entry, "choice": "uniform", "note": "no per-vertex fit: the samples carry no face/barycentrics"}, None, None
    normal, view = data["normal"].astype(float), data["view_dir"].astype(float)
    shade = forward.render_samples(coeffs, Brdf("lambert", albedo=(1.0, 1.0, 1.0)), normal, view)
    spec = (
        forward.render_samples(coeffs, replace(brdf, albedo=(0.0, 0.0, 0.0)), normal, view) if with_lobe else np.zeros_like(shade)
    )
    return albedo_from_shading(mesh, data, shade, data["radiance"].astype(float) - spec, settings, entry)


def albedo_from_shading(
    mesh, data: dict, shade: np.ndarray, target: np.ndarray, settings: Settings, entry: dict, proxy=None
) -> tuple[dict, np.ndarray | None, object]:
    """Textured vs uniform albedo from the samples' shading per unit albedo ``shade`` (N, 3) and
    their radiance less the specular part ``target`` (N, 3) (``data``: face, bary, weight,
    image_id of the same samples): the choice of :func:`choose_albedo`, for either forward model
    (pipeline.core.texture.choose_vertex_albedo); with ``proxy`` (a pipeline.proxy.Proxy of the
    mesh) solved on the proxy's vertices and interpolated to the mesh's.  -> (report entry,
    per-vertex albedo (V, 3) or None for uniform, mesh)."""
    nv = len(mesh.vertices)
    basis = None if proxy is None else texture.coarse_basis(proxy.mesh.faces, len(proxy.mesh.vertices), proxy.tri, proxy.bary)
    noise = settings.noise_floor * rms_radiance(data)
    cands, auto, rho, observed = texture.choose_vertex_albedo(
        mesh.faces,
        nv,
        data["face"],
        data["bary"].astype(float),
        fold_of(data["image_id"], settings.folds),
        data["weight"].astype(float),
        shade,
        target,
        smoothness=settings.albedo_smoothness,
        parsimony=settings.parsimony,
        noise=noise,
        basis=basis,
    )
    choice = "textured" if settings.albedo == "textured" else auto
    entry.update(
        choice=choice,
        candidates=cands,
        vertices=nv,
        vertices_with_samples=observed,
        samples=int(len(shade)),
        auto_choice=auto,
        noise=noise,
        rule=f"the fit's parsimony rule: textured only if uniform's validation RMSE > textured's x "
        f"(1 + parsimony {settings.parsimony}) + noise floor x RMS radiance ({noise:.3g})",
        folds=settings.folds,
    )
    if basis is not None:
        entry["unknowns"] = {"on": "the interreflection proxy's vertices", "count": basis.n}
    if choice != "textured":
        return entry, None, mesh
    if basis is not None:  # the proxy's albedo at the mesh's vertices
        return entry, basis.to_vertices @ np.clip(rho, 0.0, None), mesh
    return entry, np.clip(rho, 0.0, None), mesh


def texture_pattern(obs: Observations, mesh, data: dict, vertex_rho: np.ndarray) -> np.ndarray:
    """The per-vertex albedo ``vertex_rho`` (V, 3) at the samples over its weighted mean (N, 3), the
    pattern a uniform base colour times which models a texture (prt.Geometry.pattern)."""
    rho = texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), len(mesh.vertices)) @ vertex_rho
    mean = (obs.weight[:, None] * rho).sum(axis=0) / obs.weight.sum()
    return np.clip(rho, 1e-3, None) / np.maximum(mean, 1e-6)


def texture_and_residuals(
    mesh,
    data: dict,
    geo: prt.Geometry,
    obs: Observations,
    best: material_fit.MaterialFit,
    report: dict,
    settings: Settings,
    keys: list[str],
    spec: prt.SpecularTransfer | None = None,
) -> np.ndarray | None:
    """The per-vertex albedo choice (texture.albedo_from_shading on the physical shading) and the
    residual per view of the chosen model,
    a texture's colour at each sample, into ``report``; -> the per-vertex albedo (V, 3) or None.
    ``spec``: best's specular transfer to the geometry's order if already computed (final_lighting)."""
    if best.material is None or best.parts is not None:  # parts: fit_to_map's
        spec = None
    elif spec is None:
        spec = prt.specular_transfer(geo, best.material, settings.lobe_samples, settings.seed)
    shade, specular = material_fit.shading_parts(geo, best, spec)
    vertex_rho = None
    entry = {"setting": settings.albedo, "smoothness": settings.albedo_smoothness}
    if settings.albedo == "uniform":
        report["albedo"] = {**entry, "choice": "uniform", "note": "--albedo uniform: no per-vertex fit"}
    else:
        proxy = getattr(geo.renderer.mesh, "proxy", None)  # the proxy's vertices as the unknowns
        report["albedo"], vertex_rho, _ = albedo_from_shading(mesh, data, shade, obs.radiance - specular, settings, entry, proxy)
    rho = (
        best.base
        if vertex_rho is None
        else texture.interpolation_matrix(mesh.faces, data["face"], data["bary"].astype(float), len(mesh.vertices)) @ vertex_rho
    )
    report["residuals_per_view"] = residuals_per_view(obs, rho * shade + specular, data["image_id"], keys, settings.folds)
    return vertex_rho
