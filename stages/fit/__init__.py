"""fit: lighting (SH) and BRDF from the light-field samples, in frequency space, with diagnostics.

Usage: ``sigrend fit CAPTURE -w WORK [--lighting unknown|ENV.exr|lighting_sh.json]
[--brdf auto|lambert|principled|phong|microfacet|brdf.json|inline spec] [--order auto|N]``.

Modes (the inverse-rendering table, DESIGN.md "The inverse problems"):
  lighting       BRDF known (a file or inline spec), lighting unknown: regularized linear least
                 squares for the SH coefficients with per-band conditioning labels.
  brdf           lighting known (equirect EXR or lighting_sh.json), BRDF unknown: variable
                 projection (Brent's bounded search over the lobe width, non-negative LS for albedo and specular).
  factorization  both unknown: alternating lighting / BRDF fits from the Lambertian start; the
                 scale ambiguity (one per colour channel) is fixed by capture.toml
                 ``[fit] known_albedo = [r, g, b]`` or else by the default grey albedo 0.5.
  check          both known: only residuals are reported.
Model selection: the SH order (``--order auto``) and the BRDF model (``--brdf auto``) are chosen
by leave-views-out validation (folds = image_id mod ``folds``) with the parsimony rule of
pipeline.core.selection.parsimonious_choice.  Samples with visibility < ``min_visibility`` are left out.
Then textured vs uniform diffuse albedo (``--albedo``): a per-vertex albedo with the fitted lighting
and specular part fixed (pipeline.core.texture), kept only when the held-out views prefer it.
Outputs in WORK/fit/: lighting_sh.json, lighting.exr, brdf.json, report.json, lighting.png,
spectrum.png, residuals.png (+ albedo.ply when textured).  Details: docs/fit.md.

The package: settings (Settings), known (what the user gives as known), data (the samples),
convex (the R&H closed-form path), physical (shadows, interreflection, GGX: the default with a
mesh), texture (textured vs uniform albedo), outputs (the one writer of fit/); the maths are in
pipeline.core (factorization, material_search, material_fit, selection).
"""

from __future__ import annotations

from pathlib import Path

from threadpoolctl import threadpool_limits

from pipeline.errors import UserError
from pipeline.io.capture_toml import read_capture_config
from pipeline.io.chart_json import chart_path
from pipeline.io.mesh import MESH_NAMES
from pipeline.io.samples import read_samples_meta
from stages.fit.convex import fit_convex
from stages.fit.known import known_albedo_hint, parse_brdf_setting
from stages.fit.outputs import OUTPUT_NAMES
from stages.fit.physical import fit_physical
from stages.fit.settings import Settings

__all__ = ["Settings", "inputs", "outputs", "run"]


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    paths = [Path(work) / "samples.npz"]
    for spec in (settings.lighting, settings.brdf):
        if Path(spec).is_file():
            paths.append(Path(spec))
    if (Path(capture) / "capture.toml").exists():
        paths.append(Path(capture) / "capture.toml")
        try:  # the maps of a lighting per photo
            paths += [light.path for light in read_capture_config(capture).lighting.values() if light.path]
        except UserError:
            pass  # a malformed capture.toml is reported when the stage runs
    # the mesh (the physical forward model, textured albedo) and the poses (the samples' pixel footprints)
    paths += [Path(capture) / n for n in MESH_NAMES if (Path(capture) / n).exists()][:1]
    paths += [p for p in (Path(work) / "poses.json", Path(capture) / "poses.json") if p.exists()][:1]
    paths += [p for p in [chart_path(work)] if p.exists()]  # a colour chart (linearize, capture.toml [chart])
    return paths


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    return [Path(work) / "fit" / n for n in OUTPUT_NAMES]


def run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    """The fit stage (module docstring), with the BLAS thread pool limited to ``blas_threads``."""
    if settings.blas_threads == 0:
        return _run(capture=Path(capture), work=Path(work), settings=settings)
    with threadpool_limits(limits=settings.blas_threads, user_api="blas"):
        return _run(capture=Path(capture), work=Path(work), settings=settings)


def _run(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    """The physical forward model where the capture has a mesh and the material is lambert or
    principled; the convex one otherwise."""
    meta = read_samples_meta(work / "samples.npz")
    keys = meta["image_keys"]
    choice = parse_brdf_setting(settings.brdf)
    fit_model, known_brdf = choice.fit_model, choice.known
    has_mesh = any((capture / n).exists() for n in MESH_NAMES)
    if (
        settings.forward == "physical"
        and has_mesh
        and (
            fit_model in (None, "lambert", "principled") and (known_brdf is None or known_brdf.model in ("lambert", "principled"))
        )
    ):
        models = [fit_model] if fit_model else ["lambert", "principled"]
        return fit_physical(
            capture=capture,
            work=work,
            settings=settings,
            keys=keys,
            known_brdf=known_brdf,
            models=models,
            hint=known_albedo_hint(capture),
        )
    if read_capture_config(capture).lighting:
        raise UserError(
            f"{capture / 'capture.toml'}: [lighting] (a lighting per photo) is fitted on the physical "
            "forward model only: the capture needs a mesh, and --forward physical with --brdf auto, "
            "lambert or principled"
        )
    return fit_convex(
        capture=capture,
        work=work,
        settings=settings,
        keys=keys,
        fit_model=fit_model,
        known_brdf=known_brdf,
        total=int(meta.get("count", 0)),
    )
