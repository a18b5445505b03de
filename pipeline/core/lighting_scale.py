"""How bright the photos are against a known lighting: the fit's error as a function of one global
factor s of the lighting (the scale profile), measured before any material search.

Under a known lighting times s, a candidate material's radiance at a sample is s (rho Q + R) per
channel: Q its diffuse radiance per unit base colour and R its specular radiance (a dielectric's
layer, whose magnitude Fresnel fixes), both from the renderer under the map itself (or from the SH +
sources form of a lighting_sh.json) — the fit's forward model; for a metal Q is the specular per unit
F0 and R the part at F0 = 0 (Schlick's F is linear in F0).  With rho in [0, 1] per channel the best
rho at each s is least squares clipped to [0, 1], so one shading of a candidate gives its error at
every s (:func:`level_errors`, trimmed as the fit's score under a map is).  The profile is the least
error over Lambert and the principled candidates (:func:`scale_profile`).

What fixes s: a base colour (albedo, F0) at most 1 — a lower bound: a map too dim needs a base colour
above 1 — and a dielectric's Fresnel-fixed specular layer.  What does not: the level of a Lambertian
surface above that bound, and a highlight whose level trades with its width.  That trade is steep: on
a synth sphere of roughness 0.3 a candidate of roughness 0.288 reads x0.96, one of 0.300 x1.02; on
a real photographed ball (DiLiGenT's, its calibrated light) whose highlight peak is saturated the
photos accept anything from x0.50 up (a base colour at most 1) with an error within 5 % of the least.
So a factor is "measured" only as far as the profile says: the scales whose error is within
``tolerance`` (relative) plus ``noise`` of the least are all accepted (:class:`ScaleProfile`), as the
parsimony rule of pipeline.core.selection takes models within them as equal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from pipeline.core import material_fit, prt
from pipeline.core.candidate import Observations
from pipeline.core.material import MIN_ROUGHNESS, Principled, brdf_from_material
from pipeline.core.material_fit import TRIM_FRACTION
from pipeline.core.material_search import END_PROBE, LOCATE_ROUGHNESS, ROUGHNESS_XTOL
from pipeline.core.selection import descend_grid, parabola_minimum, refine_bracket
from pipeline.core.sources import Sources

SCALE_STEP = 0.02  # the profile's scales: exp(k SCALE_STEP), 2 % apart ...
SCALE_RANGE = 1e4  # ... from 1/SCALE_RANGE to SCALE_RANGE (an end reached: unbounded that way)
SCALES = np.exp(
    SCALE_STEP * np.arange(-int(round(np.log(SCALE_RANGE) / SCALE_STEP)), int(round(np.log(SCALE_RANGE) / SCALE_STEP)) + 1)
)
ONE = int(np.argmin(np.abs(np.log(SCALES))))  # SCALES[ONE] == 1.0 exactly
CHUNK = 128  # scales evaluated at once


def level_errors(
    shade: np.ndarray, specular: np.ndarray, obs: Observations, scales: np.ndarray = SCALES, trim: float = TRIM_FRACTION
) -> np.ndarray:
    """The error (S,) of radiance = s (rho shade + specular) at each of ``scales`` (S,), scored as the
    fit scores a candidate under a known map (material_fit.fit_to_map): rho (3,) the weighted least
    squares clipped to [0, 1] (closed form per scale: the sums over samples taken once; the fit's
    floor of 1e-3 left out, which would bound a dark Lambertian's factor from above), the
    weighted RMSE without the ``trim`` fraction of samples whose residual is largest
    (material_fit.trimmed_rmse, vectorized over the scales)."""
    w = obs.weight
    b = obs.radiance
    qq, qb, qr = ((w[:, None] * shade * x).sum(0) for x in (shade, b, specular))
    s = np.asarray(scales, float)
    rho = np.clip((qb / s[:, None] - qr) / np.maximum(qq, 1e-300), 0.0, 1.0)
    keep_n = int(np.floor((w.size - 1) * (1.0 - trim))) + 1  # trimmed_rmse's: e <= its (1 - trim) quantile
    out = np.empty(s.size)
    for a in range(0, s.size, CHUNK):
        sl = slice(a, a + CHUNK)
        e = ((b[None] - s[sl, None, None] * (rho[sl, None, :] * shade[None] + specular[None])) ** 2).sum(axis=2)
        keep = (e <= np.partition(e, keep_n - 1, axis=1)[:, keep_n - 1 : keep_n]) if keep_n < w.size else np.ones_like(e, bool)
        out[sl] = np.sqrt((w * e * keep).sum(axis=1) / (3 * (w * keep).sum(axis=1)))
    return out


@dataclass(frozen=True)
class ScaleProfile:
    """The profile of the fit's error over the lighting's factor s (SCALES): ``errors`` (S,) the least
    over the candidates; ``best`` the s of the least error; ``limit`` = least (1 + tolerance) + noise;
    ``accepted`` (low, high) the run of scales around ``best`` within the limit, None for an end that
    reached the grid's (the photos do not bound s that way); ``at_one`` the error at s = 1 (the map as
    given); ``candidates`` the table: per candidate its best s, least error and error at s = 1."""

    errors: np.ndarray
    best: float  # between the grid's scales: the parabola's vertex through the least and its neighbours
    limit: float
    accepted: tuple[float | None, float | None]
    at_one: float
    candidates: list[dict]

    @classmethod
    def of(cls, errors: np.ndarray, tolerance: float, noise: float, candidates: list | None = None) -> "ScaleProfile":
        """The profile of ``errors`` (S,) over SCALES, its limit = least (1 + ``tolerance``) + ``noise``."""
        best = int(np.argmin(errors))
        limit = float(errors[best] * (1.0 + tolerance) + noise)
        near = slice(max(best - 1, 0), best + 2)  # the least between the grid's scales: a parabola's vertex
        return cls(
            errors,
            parabola_minimum(SCALES[near], errors[near]),
            limit,
            _accepted_run(errors, best, limit),
            float(errors[ONE]),
            candidates or [],
        )

    @property
    def accepts_one(self) -> bool:
        """Whether the photos take the map as given (its error at s = 1 within the limit)."""
        return self.at_one <= self.limit

    def reading(self) -> tuple[str, float]:
        """What the photos say of the factor: ("about", the least-error scale) where the accepted run is
        bounded both ways, else ("at least", its lower end) or ("at most", its upper end); ("any", 1)
        when the photos bound it neither way."""
        low, high = self.accepted
        if low is not None and high is not None:
            return "about", self.best
        if low is not None:
            return "at least", low
        return ("at most", high) if high is not None else ("any", 1.0)

    def factor(self) -> float:
        """The factor to apply when the map is to be fitted: 1 where the photos accept it; else the
        least-error scale where the accepted run is bounded both ways, or its bound nearest 1."""
        return 1.0 if self.accepts_one else self.reading()[1]


def _accepted_run(errors: np.ndarray, best: int, limit: float) -> tuple[float | None, float | None]:
    ok = errors <= limit
    lo = hi = best
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    while hi < len(errors) - 1 and ok[hi + 1]:
        hi += 1
    return (None if lo == 0 else float(SCALES[lo]), None if hi == len(errors) - 1 else float(SCALES[hi]))


def scale_profile(
    shading: Callable[[Principled | None], tuple[np.ndarray, np.ndarray]],
    obs: Observations,
    roughness_grid,
    *,
    ior: float,
    tolerance: float,
    noise: float,
    refinements: int,
) -> ScaleProfile:
    """The scale profile (module docstring) of the samples ``obs`` from ``shading(material)`` ->
    (Q, R) at the map as given (None: Lambert): Lambert; a dielectric over ``roughness_grid``
    (descended from its point nearest LOCATE_ROUGHNESS to the bracket of its least error, as the
    material search does), refined by Brent's search (selection.refine_bracket, ``refinements``
    candidates at most) at its least error, then at the parabola's vertex through its best three; a
    metal at that roughness, and only where it does better there, over the grid from it outwards
    (selection.descend_grid) and refined likewise; and where no candidate takes the map as given
    yet, each family refined again at its error at s = 1.
    ``tolerance``, ``noise``: the limit (ScaleProfile)."""
    families: dict = {None: {}, 0.0: {}, 1.0: {}}

    def fit_at(metallic: float | None, r: float) -> np.ndarray:
        fits = families[metallic]
        if r not in fits:
            material = None if metallic is None else Principled(roughness=float(r), metallic=metallic, ior=ior)
            fits[r] = level_errors(*shading(material), obs)
        return fits[r]

    def least(e: np.ndarray) -> float:
        return float(e.min())

    def at_one(e: np.ndarray) -> float:
        return float(e[ONE])

    def refine(metallic: float, score) -> None:
        fits = families[metallic]
        if len(fits) > 1:
            refine_bracket(
                fits,
                lambda r: fit_at(metallic, r),
                score,
                refinements,
                low_end=MIN_ROUGHNESS,
                high_end=1.0,
                xtol=ROUGHNESS_XTOL,
                end_probe=END_PROBE,
            )
            # and the parabola's vertex through the best three: the reading moves with the roughness (a
            # highlight's level trades with its width: 4 % of roughness, 6 % of scale at 0.3)
            rs = np.array(sorted(fits))
            vertex = parabola_minimum(rs, np.array([score(fits[r]) for r in rs]))
            if np.min(np.abs(np.log(rs / vertex))) > ROUGHNESS_XTOL / 2:
                fit_at(metallic, vertex)

    def profile() -> np.ndarray:
        return np.min(np.stack([e for fits in families.values() for e in fits.values()]), axis=0)

    grid = [float(r) for r in roughness_grid]
    fit_at(None, 0.0)
    first = int(np.argmin([abs(np.log(r / LOCATE_ROUGHNESS)) for r in grid]))
    descend_grid(grid, lambda r: least(fit_at(0.0, r)), first)
    refine(0.0, least)
    start = min(families[0.0], key=lambda r: least(families[0.0][r]))
    metals = [1.0] if least(fit_at(1.0, start)) < least(families[0.0][start]) else []
    if metals:  # a metal only where it does better at the dielectric's best roughness (as select_material)
        grid_start = min(grid, key=lambda r: abs(np.log(r / start)))
        descend_grid(grid, lambda r: least(fit_at(1.0, r)), grid.index(grid_start))
        refine(1.0, least)
    errors = profile()
    if errors[ONE] > errors.min() * (1.0 + tolerance) + noise:  # the map as given: its best roughness too
        for metallic in (0.0, *metals):
            refine(metallic, at_one)
        errors = profile()
    rows = [
        {
            "name": "lambert" if m is None else f"{'metal' if m else 'dielectric'} roughness {r:.3f}",
            "best_scale": float(SCALES[int(np.argmin(e))]),
            "least_rmse": float(e.min()),
            "rmse_at_given": float(e[ONE]),
        }
        for m, fits in families.items()
        for r, e in sorted(fits.items())
    ]
    return ScaleProfile.of(errors, tolerance, noise, rows)


def map_shading(scene, direct, geo: prt.Geometry, base: np.ndarray, scale: float) -> Callable:
    """shading(material) -> (Q, R) at the samples of ``geo`` under a known map: ``scene`` its
    pipeline.core.render Renderer (or SceneGroups), ``direct`` the scene's direct_parts at these
    samples, the map times ``scale``; the interreflection at the grey ``base``.  The scene's
    bounce rays are cast here, once, so that its copies for each material (with_brdf) share them."""
    for one in getattr(scene, "scenes", [scene]):
        one.vertex_scene.bounce_rays()

    def shading(material: Principled | None) -> tuple[np.ndarray, np.ndarray]:
        def parts(b) -> tuple[np.ndarray, np.ndarray]:
            r = scene.with_brdf(brdf_from_material(material, np.asarray(b, float)))
            d, s = r.shade_parts(geo.faces, geo.bary, geo.view_dirs, direct, geo.footprint)
            return d * scale, s * scale

        if material is not None and material.metallic > 0:
            zero, one = parts(np.zeros(3))[1], parts(np.ones(3))[1]
            return one - zero, zero
        return parts(base)

    return shading


def sh_shading(
    geo: prt.Geometry,
    coeffs: np.ndarray,
    directions: np.ndarray,
    intensity: np.ndarray,
    base: np.ndarray,
    lobe_samples: int,
    seed: int,
) -> Callable:
    """shading(material) -> (Q, R) at the samples of ``geo`` under a lighting given as SH ``coeffs`` +
    directional sources (``directions``, ``intensity``; the transfer of pipeline.core.prt, as
    material_fit.shading_parts), the interreflection at the grey ``base``."""

    def shading(material: Principled | None) -> tuple[np.ndarray, np.ndarray]:
        spec = None if material is None else prt.specular_transfer(geo, material, lobe_samples, seed)
        sources = None
        if directions is not None and len(directions):
            sources = Sources(prt.source_transfer(geo, material, directions), intensity)
        fit = material_fit.MaterialFit(material, np.asarray(base, float), coeffs, None, [], 0.0, 0.0, sources)
        return material_fit.shading_parts(geo, fit, spec)

    return shading


def scene_rows(scene, direct, rows: np.ndarray) -> tuple:
    """(scene, direct) of a known map for the samples ``rows`` (sorted indices) of those they were
    made for: a Renderer's direct_parts sliced; a SceneGroups (a lighting per photo) regrouped, each
    scene's direct_parts sliced to its rows among them."""
    if hasattr(scene, "scenes"):
        group = scene.group[rows]
        parts = []
        for g, full in enumerate(scene._rows()):
            pos = np.searchsorted(full, rows[group == g])
            parts.append((direct[g][0][pos], direct[g][1][pos]))
        return type(scene)(scene.scenes, group), parts
    return scene, (direct[0][rows], direct[1][rows])
