"""BRDF models: the material type every stage passes (``Brdf``, one parameter table) and the seed
theory's formulas in the angular domain (DESIGN.md, brdf.json; the principled model's are in
pipeline.core.material).

All directions are unit vectors (N, 3) in the same frame; ``w_in`` points from the surface
towards the light, ``w_out`` towards the viewer.  Values are per RGB channel, (N, 3).

  lambert      f = rho_d / pi
  phong        f = rho_d / pi + k_s (s + 1) / (2 pi) max(0, r . w_in)^s / (n . w_in)
               with k_s = specular_weight, s = exponent and r = reflect(w_out, n): R&H 2001's
               reflection-space Phong, whose *transfer* f cos(theta_in) is a lobe symmetric about
               r with unit integral over the sphere, so its SH filter is exactly radial (A_0 = k_s;
               A_l ~ exp(-l^2 / 2s)).
  microfacet   f = rho_d / pi + F(w_in . h) D(h) G / (4 (n . w_in)(n . w_out))   (Torrance-Sparrow)
               Beckmann D(h) = exp(-tan^2 theta_h / sigma^2) / (pi sigma^2 cos^4 theta_h) with
               sigma = beckmann_sigma (RMS microfacet slope), Schlick F = F0 + (1 - F0)(1 - c)^5
               with F0 = f0, Cook-Torrance V-cavity G = min(1, 2 (n.h)(n.w_out)/(w_out.h),
               2 (n.h)(n.w_in)/(w_out.h)).  R&H approximate its filter by exp(-(sigma l)^2).
Both sides are zero when either direction is below the surface.  lobe_over_directions sums the
phong and microfacet lobes over a light set (pipeline.core.light_set) on their support (lobe_support_cut).

Each parameter name has one meaning: ``roughness`` is only the principled model's perceptual
roughness (GGX alpha = roughness^2), the microfacet model's Beckmann RMS slope is ``beckmann_sigma``;
Phong's lobe weight is ``specular_weight``, the microfacet model's Fresnel reflectance at normal
incidence ``f0``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Literal

import numpy as np

_EPS = 1e-12

BrdfModel = Literal["lambert", "principled", "phong", "microfacet"]
RGB = tuple[float, float, float]
# The one parameter table: each model's parameters in brdf.json's order (pipeline.io.brdf says
# their ranges).  principled is Blender's Principled BSDF / glTF 2.0 metallic-roughness
# (pipeline.core.material); phong and microfacet are the seed theory's (this module).
BRDF_PARAMS: dict[str, tuple[str, ...]] = {
    "lambert": ("albedo",),
    "principled": ("base_color", "roughness", "metallic", "ior", "specular_tint"),
    "phong": ("albedo", "specular_weight", "exponent"),
    "microfacet": ("albedo", "f0", "beckmann_sigma"),
}
PARAM_DEFAULTS = {"metallic": 0.0, "ior": 1.5, "specular_tint": (1.0, 1.0, 1.0)}  # principled's optional ones
RGB_PARAMS = ("albedo", "specular_weight", "f0", "base_color", "specular_tint")
LOBE_MODELS = ("phong", "microfacet")  # the seed's models with R&H's reflection-space lobe
WIDTH_PARAM = {"phong": "exponent", "microfacet": "beckmann_sigma"}  # the lobe's width parameter
# the lobe's RGB parameter, linear in the radiance: Phong's weight k_s, the microfacet's Schlick F0
LOBE_COLOR_PARAM = {"phong": "specular_weight", "microfacet": "f0"}


@dataclass(frozen=True)
class Brdf:
    """One uniform material: ``model`` and its parameters (``BRDF_PARAMS[model]``; the others are
    None).  RGB parameters are 3 linear floats, the rest floats; a principled material's optional
    parameters get ``PARAM_DEFAULTS``.  Structure only: pipeline.io.brdf checks ranges for users.
    """

    model: BrdfModel
    albedo: RGB | None = None
    specular_weight: RGB | None = None
    exponent: float | None = None
    f0: RGB | None = None
    beckmann_sigma: float | None = None
    base_color: RGB | None = None
    roughness: float | None = None
    metallic: float | None = None
    ior: float | None = None
    specular_tint: RGB | None = None

    def __post_init__(self) -> None:
        if self.model not in BRDF_PARAMS:
            raise ValueError(f"unknown BRDF model {self.model!r}; one of {', '.join(BRDF_PARAMS)}")
        params = BRDF_PARAMS[self.model]
        for f in fields(self)[1:]:
            value = getattr(self, f.name)
            if f.name not in params:
                if value is not None:
                    raise ValueError(f"a {self.model} BRDF has no parameter {f.name!r}")
                continue
            if value is None:
                value = PARAM_DEFAULTS.get(f.name)
                if value is None:
                    raise ValueError(f"a {self.model} BRDF needs {f.name!r}")
            if f.name in RGB_PARAMS:
                rgb = np.broadcast_to(np.asarray(value, float), (3,))
                value = tuple(float(v) for v in rgb)
            else:
                value = float(value)
            object.__setattr__(self, f.name, value)

    @classmethod
    def from_dict(cls, doc: Mapping) -> "Brdf":
        """From a brdf.json-shaped mapping: ``model`` and its parameters; other keys are ignored."""
        model = doc["model"]
        return cls(model, **{k: doc[k] for k in BRDF_PARAMS.get(model, ()) if k in doc})

    def to_dict(self) -> dict:
        """The brdf.json form (JSON types: lists for RGB)."""
        out: dict = {"model": self.model}
        for key in BRDF_PARAMS[self.model]:
            value = getattr(self, key)
            out[key] = list(value) if key in RGB_PARAMS else value
        return out

    @property
    def diffuse_color(self) -> np.ndarray:
        """The Lambertian colour (3,): ``albedo``, or a principled material's ``base_color``."""
        return np.array(getattr(self, self._diffuse_param), float)

    def with_diffuse_color(self, color) -> "Brdf":
        """The same material with another diffuse colour (3,) (albedo or base colour)."""
        return replace(self, **{self._diffuse_param: color})

    @property
    def _diffuse_param(self) -> str:
        return BRDF_PARAMS[self.model][0]  # every model's first parameter is its diffuse colour

    @property
    def has_lobe(self) -> bool:
        """A seed model with R&H's reflection-space lobe (phong, microfacet)."""
        return self.model in LOBE_MODELS

    @property
    def lobe_width(self) -> float:
        """The lobe's width parameter (Phong exponent s or Beckmann sigma) of a ``has_lobe`` model."""
        return float(getattr(self, WIDTH_PARAM[self.model]))

    @property
    def lobe_color(self) -> np.ndarray:
        """The lobe's RGB parameter (3,) of a ``has_lobe`` model: Phong's specular_weight or the
        microfacet's f0 (LOBE_COLOR_PARAM)."""
        return np.array(getattr(self, LOBE_COLOR_PARAM[self.model]), float)

    def with_lobe_color(self, color) -> "Brdf":
        """The same ``has_lobe`` material with another lobe colour (3,) (specular_weight or f0)."""
        return replace(self, **{LOBE_COLOR_PARAM[self.model]: color})

    @classmethod
    def from_lobe(cls, model: str, albedo, lobe_color, lobe_width: float) -> "Brdf":
        """A phong or microfacet material from its albedo, lobe colour and lobe width (the
        solvers' generic parameters; LOBE_COLOR_PARAM and WIDTH_PARAM name them)."""
        return cls(model, albedo=albedo, **{LOBE_COLOR_PARAM[model]: lobe_color, WIDTH_PARAM[model]: lobe_width})


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def reflect(w: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror direction of unit ``w`` about unit ``normal``: 2 (n . w) n - w, (N, 3)."""
    w = np.atleast_2d(w)
    n = np.atleast_2d(normal)
    return 2.0 * _dot(n, w)[:, None] * n - w


def beckmann_distribution(cos_h: np.ndarray, beckmann_sigma: float) -> np.ndarray:
    """Beckmann D(h) for cos(theta_h) = n . h and RMS slope sigma; normalized so that
    integral D cos(theta_h) dw = 1."""
    c2 = np.clip(cos_h, _EPS, 1.0) ** 2
    tan2 = (1.0 - c2) / c2
    d = np.exp(-tan2 / beckmann_sigma**2) / (np.pi * beckmann_sigma**2 * c2 * c2)
    return np.where(cos_h > 0, d, 0.0)


def schlick_fresnel(cos_i: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """Schlick's Fresnel F = F0 + (1 - F0)(1 - cos)^5; cos (N,), F0 (3,) -> (N, 3)."""
    c = np.clip(cos_i, 0.0, 1.0)[:, None]
    f0 = np.asarray(f0, dtype=float)[None, :]
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def vcavity_shadowing(n_h, n_in, n_out, out_h) -> np.ndarray:
    """Cook-Torrance V-cavity shadowing-masking G (N,)."""
    out_h = np.maximum(out_h, _EPS)
    return np.minimum(1.0, np.minimum(2.0 * n_h * n_out / out_h, 2.0 * n_h * n_in / out_h))


def phong_lobe(cos_alpha: np.ndarray, exponent: float) -> np.ndarray:
    """R&H reflection-space Phong lobe (s + 1)/(2 pi) max(0, cos alpha)^s: unit integral over the sphere."""
    return (exponent + 1.0) / (2.0 * np.pi) * np.maximum(cos_alpha, 0.0) ** exponent


def cosine_weighted_brdf(brdf: Brdf, normal: np.ndarray, w_in: np.ndarray, w_out: np.ndarray) -> np.ndarray:
    """The transfer f(w_in, w_out) max(0, n . w_in): what the reflection equation integrates. (N, 3)."""
    n, wi, wo = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (normal, w_in, w_out))
    n_in, n_out = _dot(n, wi), _dot(n, wo)
    front = (n_in > 0) & (n_out > 0)
    cos_in = np.where(front, n_in, 0.0)
    albedo = np.asarray(brdf.albedo, dtype=float)
    value = (cos_in / np.pi)[:, None] * albedo[None, :]
    model = brdf.model
    if model == "phong":
        lobe = phong_lobe(_dot(reflect(wo, n), wi), brdf.exponent)
        value = value + np.where(front, lobe, 0.0)[:, None] * np.asarray(brdf.specular_weight, float)[None, :]
    elif model == "microfacet":
        h = wi + wo
        h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), _EPS)
        n_h, out_h = _dot(n, h), _dot(wo, h)
        d = beckmann_distribution(n_h, brdf.beckmann_sigma)
        g = vcavity_shadowing(n_h, np.maximum(n_in, 0), np.maximum(n_out, 0), out_h)
        f = schlick_fresnel(_dot(wi, h), brdf.f0)
        spec = np.where(front, d * g / (4.0 * np.maximum(n_out, _EPS)), 0.0)  # cos_in cancels
        value = value + spec[:, None] * f
    elif model != "lambert":
        raise ValueError(f"unknown BRDF model {model!r}")
    return value


def brdf_value(brdf: Brdf, normal: np.ndarray, w_in: np.ndarray, w_out: np.ndarray) -> np.ndarray:
    """f(w_in, w_out) in 1/sr, (N, 3); zero below either horizon (see the module docstring)."""
    n_in = _dot(np.atleast_2d(normal), np.atleast_2d(w_in))
    return cosine_weighted_brdf(brdf, normal, w_in, w_out) / np.maximum(n_in, _EPS)[:, None]


LOBE_CUT_SIGMAS = 4.0  # microfacet support: tan(theta_h) < 4 sigma, D > exp(-16) of its peak
PHONG_CUT = 1e-7  # phong support: cos(alpha)^s > 1e-7


def lobe_support_cut(brdf: Brdf) -> float | None:
    """cos of the largest angle between w_in and the mirror direction r of w_out at which the seed
    models' lobe is not negligible (None for a model without one): for Beckmann sigma σ the half
    vector is more than atan(4σ) from n (D < e^-16 of its peak) whenever w_in is more than 2 atan(4σ)
    from r (reflecting w_out about h instead of n is r rotated by twice the angle between h and n);
    for Phong where cos^s < 1e-7."""
    model = brdf.model
    if model == "microfacet":
        return float(np.cos(min(np.pi, 2.0 * np.arctan(LOBE_CUT_SIGMAS * brdf.beckmann_sigma))))
    if model == "phong":
        return float(max(0.0, np.exp(np.log(PHONG_CUT) / brdf.exponent)))
    return None


def lobe_over_directions(
    brdf: Brdf,
    n: np.ndarray,
    wo: np.ndarray,
    n_out: np.ndarray,
    cos_in: np.ndarray,
    vis: np.ndarray | None,
    spec_cut: float,
    dirs: np.ndarray,
    power: np.ndarray,
) -> np.ndarray:
    """Specular lobe of a phong or microfacet ``brdf`` summed over directions ``dirs`` (D, 3) with
    power L dω ``power`` (D, 3) for P points of unit normals ``n`` and view directions ``wo`` (P, 3):
    radiance (P, 3), on the lobe's support only (``spec_cut``: lobe_support_cut).

    ``n_out`` = n . w_o (P, 1); ``cos_in`` = n . w_j where both are positive, else 0 (P, D);
    ``vis`` interpolated visibility (P, D) or None.  Dense over the pairs, with the half
    vector never formed: |w_j + w_o|^2 = 2 + 2 w_o . w_j, so n . h = (n . w_j + n . w_o) /
    |w_j + w_o| and w_o . h = w_j . h = (1 + w_o . w_j) / |w_j + w_o|.  Schlick's F is linear
    in F0, so F0 (RGB) is applied after the sum over directions.
    """
    r = 2.0 * n_out * n - wo  # mirror direction of w_o
    r_w = r @ dirs.T
    support = (cos_in > 0) & (r_w > spec_cut)
    if vis is not None:
        support &= vis > 0
    lobe_color = brdf.lobe_color  # Phong's specular_weight or the microfacet's f0
    if brdf.model == "phong":
        # R&H reflection-space Phong: the transfer f cos(theta_in) is the lobe itself
        transfer = np.where(support, phong_lobe(r_w, brdf.exponent), 0.0)
        if vis is not None:
            transfer = transfer * vis
        return lobe_color[None, :] * (transfer @ power)
    wo_w = wo @ dirs.T
    inv_len = 1.0 / np.sqrt(np.maximum(2.0 + 2.0 * wo_w, 1e-12))
    n_h = np.where(support, (cos_in + n_out) * inv_len, 1.0)
    out_h = np.where(support, (1.0 + wo_w) * inv_len, 1.0)
    d = beckmann_distribution(n_h, brdf.beckmann_sigma)
    g = vcavity_shadowing(n_h, cos_in, n_out, out_h)
    # f cos(theta_in) = F D G / (4 n . w_out) (Torrance-Sparrow; cos(theta_in) cancels)
    transfer = np.where(support, d * g, 0.0) / (4.0 * np.maximum(n_out, 1e-12))
    if vis is not None:
        transfer = transfer * vis
    schlick = (1.0 - np.clip(out_h, 0.0, 1.0)) ** 5
    s1, s2 = transfer @ power, (transfer * schlick) @ power
    return lobe_color[None, :] * s1 + (1.0 - lobe_color[None, :]) * s2
