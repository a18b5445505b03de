"""The fit stage's settings: one frozen dataclass whose field docs are `sigrend fit --help`
(pipeline.settings), validated once; list settings are parsed by properties (band_priors,
roughness_grid) and the core solvers get typed options built from them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pipeline.core.factorization import ConvexOptions
from pipeline.core.material import MIN_ROUGHNESS
from pipeline.errors import UserError
from pipeline.memory import Budget
from pipeline.proxy import PROXY_PIXELS
from pipeline.settings import memory_limit_setting, setting

DEFAULT_ALBEDO = 0.5  # the scale convention of a Lambertian fit under unknown lighting when no hint is given


@dataclass(frozen=True)
class Settings:
    lighting: str = setting("unknown", "'unknown', or the known lighting: an equirect EXR/HDR (DESIGN.md) or a lighting_sh.json")
    brdf: str = setting(
        "auto",
        "'auto': the material chosen by the held-out views, with a mesh (--forward physical) "
        "among lambert and principled (a dielectric, or a metal where it does better), "
        "without one (or --forward convex) among lambert, phong and microfacet; a model "
        "name (lambert, principled, phong, microfacet), its parameters fitted; or a known "
        "BRDF: brdf.json path or inline spec 'model:key=v,...'",
    )
    order: str = setting("auto", "SH order of the fitted lighting: 'auto' (leave-views-out validation) or an integer")
    max_order: int = setting(
        16,
        "largest SH order tried by --order auto for the final lighting, with the prior "
        "scales of --band-prior-choices (sharp lights seen through a glossy lobe carry "
        "energy to order > 8)",
    )
    factor_order: int = setting(
        8, "SH order of the lighting while the material is chosen (the final lighting is then chosen up to --max-order for it)"
    )
    env_order: int = setting(16, "SH order to which a known EXR lighting is projected")
    lobe_min_cos: float = setting(
        0.3,
        "with a specular lobe in the model, use only samples with n.v >= this: the R&H "
        "reflection-space lobe is accurate near normal view (docs/fit.md)",
    )
    min_visibility: float = setting(0.9, "leave out samples whose unblocked hemisphere fraction is below this")
    folds: int = setting(4, "validation folds; views go to fold image_id mod folds")
    parsimony: float = setting(0.05, "choose the smallest model whose validation RMSE is within this fraction of the best")
    noise_floor: float = setting(0.005, "noise assumed at least this fraction of the RMS radiance (calibration, model error)")
    min_snr: float = setting(10.0, "a band is recoverable when its SNR (docs/fit.md) reaches this")
    band_prior: float = setting(0.3, "Tikhonov prior scale of ill-conditioned bands, as a fraction of the DC lighting")
    band_prior_choices: str = setting(
        "1,3",
        "further prior scales tried with --order auto; order and prior are "
        "chosen together by leave-views-out validation (sharp lights put "
        "more energy in high bands than the default prior allows)",
    )
    iterations: int = setting(3, "alternations lighting <-> BRDF in the factorization after the joint linear start")
    max_samples: int = setting(400000, "samples held in memory for BRDF and factorization fits (random subset)")
    chunk: int = setting(262144, "samples per chunk when streaming the normal equations")
    env_height: int = setting(64, "height of fit/lighting.exr (width = 2 x height)")
    seed: int = setting(0, "random seed of the sample subset")
    albedo: Literal["auto", "uniform", "textured"] = setting(
        "auto",
        "diffuse albedo: 'uniform', 'textured' (per vertex, fit/albedo.ply) or 'auto' "
        "(textured only if it beats uniform on the held-out views by more than --parsimony)",
    )
    albedo_smoothness: float = setting(
        0.001,
        "weight of the mesh-Laplacian smoothness term of the per-vertex albedo (relative to the mean data weight per vertex); "
        "a material map tries it, x100 and x10^4 and keeps the best on the held-out views",
    )
    texels: Literal["off", "auto"] = setting(
        "auto",
        "physical fit: a base colour per texel of a UV atlas at the photos' footprint "
        "(the mesh's own UVs, else an xatlas unwrap) from every sample, over the per-vertex "
        "albedo refitted on every sample; 'auto' runs where the sample subset chose a "
        "texture or was too thin to decide (under two samples per vertex and fold) and keeps "
        "each level where the held-out views improve (fit/textures/)",
    )
    materials: Literal["one", "auto"] = setting(
        "auto",
        "physical fit, material unknown: 'one' material over the surface, or 'auto': where "
        "some patches' radiance changes with the view far more than the rest's (a metal "
        "seed), a metal and a body under one lighting, kept where they beat one material "
        "on held-out samples, then each vertex taking the one that explains its samples "
        "(fit/material.ply, brdf.json 'materials') where the held-out views prefer the map "
        "to one material; without a seed 'auto' costs the view spread alone",
    )
    forward: Literal["physical", "convex"] = setting(
        "physical",
        "forward model of the fit: 'physical' (the renderer's: shadows, "
        "interreflection, principled GGX, directional sources; lambert and principled) "
        "or 'convex' (R&H closed forms; the only one for phong and microfacet)",
    )
    lighting_scale: str = setting(
        "1",
        "factor applied to a known --lighting (a number), or 'fit': one global "
        "factor fitted to the photos (stated in the report)",
    )
    roughness_candidates: str = setting(
        "0.1,0.2,0.3,0.45,0.65,1.0", "principled fit: the roughness grid compared on held-out views (the best is then refined)"
    )
    roughness_refinements: int = setting(
        4,
        "principled fit: most candidates of a bounded Brent search in log "
        "roughness between the best grid point's neighbours; 0 = one candidate at "
        "the parabola through the three",
    )
    ior: float = setting(1.5, "principled fit: index of refraction of the dielectric specular layer")
    max_sources: int = setting(
        3,
        "principled fit: directional sources (the lighting's dual angular part) tried "
        "on top of the SH lighting, each kept only if it lowers the held-out views' error by 2%",
    )
    source_peaks: int = setting(
        3,
        "principled fit, a sharp lobe (roughness below ~0.31): once the material is "
        "chosen, its sources' pursuit is continued with this many candidates a step from "
        "the peaks of the residual at the samples' mirror directions (lamps the direction "
        "set's scan falls between), kept where the held-out views prefer it; 0 = off",
    )
    peak_sources: int = setting(6, "most directional sources of that continued pursuit")
    lighting_detail: Literal["auto", "off"] = setting(
        "auto",
        "principled fit, lighting unknown: 'auto' tries the lighting's detail part (a map of what the SH "
        "bands cannot hold, seen through the specular lobe only) at the best dielectric when its lobe is sharp "
        "enough, and keeps it, searching the roughness again with it, where it lowers the held-out views' "
        "error by 2%; 'off'",
    )
    physical_samples: int = setting(30000, "principled fit: samples used (random subset)")
    memory_limit: str = memory_limit_setting()
    lobe_samples: int = setting(32, "principled fit: GGX lobe samples per sample in the specular transfer")
    bounce_samples: int = setting(64, "principled fit: occlusion / bounce rays per vertex (shadows, interreflection)")
    proxy_pixels: float = setting(
        PROXY_PIXELS,
        "principled fit: a mesh much finer than the photos resolve (more than twice the "
        "faces of edges this many photo pixels long) gets a simplified proxy of such "
        "edges for its interreflection (pipeline/proxy.py); 0: never",
    )
    noise_model: Literal["measured", "uniform"] = setting(
        "measured",
        "principled fit: 'measured' (samples weighted by 1 / sigma^2 of the "
        "Poisson-Gaussian noise level measured on the photos: bright pixels are "
        "noisier) or 'uniform' (equal weights)",
    )
    footprint: int = setting(
        2,
        "principled fit: n x n rays per sample's pixel; the specular of sharp lights "
        "(directional sources, a known map's bright pixels) is averaged over the surface "
        "they hit, as the pixel averages it (1: the pixel centre only)",
    )
    blas_threads: int = setting(
        1,
        "BLAS threads during the fit (0 = library default); the fit's many small "
        "products ran 7x slower with multithreaded OpenBLAS on a shared 2-core machine",
    )

    @property
    def known_lighting_file(self) -> Path | None:
        """--lighting as the known lighting's file, or None for 'unknown'; a user error when the file is missing."""
        if self.lighting == "unknown":
            return None
        path = Path(self.lighting)
        if not path.is_file():
            raise UserError(
                f"--lighting {self.lighting!r}: no such file; give 'unknown', an equirect EXR/HDR or a lighting_sh.json"
            )
        return path

    @property
    def explicit_order(self) -> int | None:
        """--order as a number, or None for 'auto' (checked by validate)."""
        return None if self.order == "auto" else int(self.order)

    @property
    def band_priors(self) -> tuple[float, ...]:
        """--band-prior first, then the distinct --band-prior-choices."""
        extra = [float(x) for x in self.band_prior_choices.split(",") if x.strip()]
        return (self.band_prior, *[p for p in dict.fromkeys(extra) if p != self.band_prior])

    @property
    def roughness_grid(self) -> tuple[float, ...]:
        """--roughness-candidates as sorted distinct numbers; a user error outside [MIN_ROUGHNESS, 1]."""
        try:
            values = sorted({float(x) for x in self.roughness_candidates.split(",") if x.strip()})
        except ValueError:
            values = []
        if not values or values[0] < MIN_ROUGHNESS or values[-1] > 1.0:
            raise UserError(
                f"--roughness-candidates must be comma-separated numbers in [{MIN_ROUGHNESS}, 1], "
                f"got {self.roughness_candidates!r}"
            )
        return tuple(values)

    @property
    def candidate_order(self) -> int:
        """The SH order the material candidates are fitted and compared at."""
        return self.factor_order if self.explicit_order is None else self.explicit_order

    def convex_options(self) -> ConvexOptions:
        """The convex solvers' numbers (pipeline.core.factorization)."""
        return ConvexOptions(
            folds=self.folds,
            noise_floor=self.noise_floor,
            min_snr=self.min_snr,
            band_priors=self.band_priors,
            parsimony=self.parsimony,
            iterations=self.iterations,
            chunk=self.chunk,
        )

    def validate(self) -> None:
        if self.order != "auto":
            try:
                if int(self.order) < 0:
                    raise ValueError
            except ValueError:
                raise UserError(f"--order must be 'auto' or a non-negative integer, got {self.order!r}") from None
        if self.max_order < 0 or self.env_order < 0 or self.factor_order < 0:
            raise UserError("--max-order, --factor-order and --env-order must be >= 0")
        try:
            if any(p <= 0 for p in self.band_priors):
                raise ValueError
        except ValueError:
            raise UserError(
                f"--band-prior-choices must be comma-separated positive numbers, got {self.band_prior_choices!r}"
            ) from None
        if self.albedo_smoothness < 0:
            raise UserError(f"--albedo-smoothness must be >= 0, got {self.albedo_smoothness}")
        if self.folds < 2:
            raise UserError(f"--folds must be >= 2 (views are held out for validation), got {self.folds}")
        if not 0.0 <= self.min_visibility <= 1.0:
            raise UserError(f"--min-visibility must be in [0, 1], got {self.min_visibility}")
        if self.ior < 1.0:
            raise UserError(f"--ior must be >= 1, got {self.ior}")
        if self.lighting_scale != "fit":
            try:
                if float(self.lighting_scale) <= 0:
                    raise ValueError
            except ValueError:
                raise UserError(f"--lighting-scale must be a positive number or 'fit', got {self.lighting_scale!r}") from None
        _ = self.roughness_grid  # a user error for a malformed grid
        if self.roughness_refinements < 0:
            raise UserError(f"--roughness-refinements must be >= 0, got {self.roughness_refinements}")
        if not 0 <= self.source_peaks <= 10:
            raise UserError(f"--source-peaks must be 0 to 10, got {self.source_peaks}")
        if self.peak_sources < 0:
            raise UserError(f"--peak-sources must be >= 0, got {self.peak_sources}")
        Budget.of(self.memory_limit)  # a bad size is one line
        if self.max_sources < 0 or self.physical_samples < 100 or self.lobe_samples < 1 or self.bounce_samples < 1:
            raise UserError("--max-sources must be >= 0, --physical-samples >= 100, --lobe-samples and --bounce-samples >= 1")
        if not self.proxy_pixels >= 0:
            raise UserError(f"--proxy-pixels must be >= 0 (0: no proxy), got {self.proxy_pixels}")
        if not 1 <= self.footprint <= 8:
            raise UserError(f"--footprint must be 1 to 8 rays per pixel axis, got {self.footprint}")
        if self.blas_threads < 0:
            raise UserError(f"--blas-threads must be >= 0, got {self.blas_threads}")
        if self.max_samples < 100 or self.chunk < 100 or self.env_height < 4 or self.iterations < 1:
            raise UserError("--max-samples, --chunk must be >= 100, --env-height >= 4, --iterations >= 1")
