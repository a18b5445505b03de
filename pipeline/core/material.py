"""Materials users' tools share: Lambert and Blender's Principled BSDF (v2) / glTF 2.0 metallic-roughness.

Conventions (DESIGN.md, docs/material.md).  Directions are unit vectors; ``w_in`` points from the
surface to the light, ``w_out`` to the viewer; mu = cos of a direction's angle to the normal.

``principled`` = a Lambertian base under a GGX specular layer, as Cycles 4.x builds it
(intern/cycles/kernel/svm/closure.h, Principled; kernel/closure/bsdf_microfacet.h):

* alpha = roughness^2 (roughness is perceptual, as Blender's slider and glTF's roughnessFactor).
* GGX (Trowbridge-Reitz) D(h) = alpha^2 / (pi (1 + (alpha^2 - 1) (n.h)^2)^2)   (Walter et al. 2007, eq. 33)
* height-correlated Smith G2 = 1 / (1 + Lambda(mu_in) + Lambda(mu_out)),
  Lambda(mu) = (sqrt(1 + alpha^2 tan^2) - 1) / 2                          (Heitz 2014, eqs. 72, 99)
* single scattering f_ss = F(w_in.h) D G2 / (4 mu_in mu_out).
* dielectric Fresnel F: exact unpolarized from ``ior`` with the specular tint as Blender's
  generalized Schlick with exponent -ior: F = F0t + (1 - F0t) s, s = (F_real - F0) / (1 - F0),
  F0t = F0(ior) tint (tint white: F = F_real).  Metal: Schlick F = F0 + (1 - F0)(1 - c)^5 with
  F0 = base colour (Cycles' F82-tint model with a white tint).
* multiple scattering (Kulla & Conty 2017, as Cycles' microfacet_ggx_preserve_energy): the lobe
  is scaled by 1 + Fms (1 - E(mu_out)) / E(mu_out), Fms = Fss E_avg / (1 - Fss (1 - E_avg)), with
  E(mu) the directional albedo of f_ss with F = 1, E_avg = 2 int E(mu) mu dmu and Fss = 2 int F mu dmu.
* layering (Cycles' closure_layering_weight): the diffuse base is weighted by
  1 - max_rgb A_spec(mu_out), A_spec = the specular layer's own directional albedo at the view.
* metallic m mixes: f = (1 - m) (dielectric specular + attenuated Lambert) + m (metal specular).

The directional albedos are computed here by quadrature over the GGX distribution of visible
normals (Heitz 2018): for fixed alpha they are 1-D functions of mu, tabulated on Gauss-Legendre
nodes once per material and interpolated.  Everything is pure NumPy.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.core.quadrature import gauss_legendre

_EPS = 1e-12
MIN_ROUGHNESS = 0.02  # alpha 4e-4: below this the lobe is narrower than any map's pixels
_ALBEDO_NODES = 48  # Gauss-Legendre nodes in mu of the directional albedo tables
_VNDF_GRID = 48  # (n x n) Gauss-Legendre rule on the VNDF's unit square per node


# --------------------------------------------------------------------------------------- GGX pieces


def ggx_distribution(cos_h: np.ndarray, alpha: float) -> np.ndarray:
    """GGX D(h) for cos_h = n.h; int D(h) (n.h) dω_h = 1 over the hemisphere."""
    c2 = np.square(np.asarray(cos_h, float))
    a2 = alpha * alpha
    d = a2 / (np.pi * np.square(1.0 + (a2 - 1.0) * c2))
    return np.where(np.asarray(cos_h) > 0, d, 0.0)


def smith_lambda(mu: np.ndarray, alpha: float) -> np.ndarray:
    """GGX Smith Lambda(mu) = (sqrt(1 + alpha^2 tan^2 theta) - 1) / 2 (Heitz 2014, eq. 72)."""
    c2 = np.clip(np.square(np.asarray(mu, float)), _EPS, 1.0)
    return 0.5 * (np.sqrt(1.0 + alpha * alpha * np.maximum(1.0 / c2 - 1.0, 0.0)) - 1.0)


def smith_g1(mu: np.ndarray, alpha: float) -> np.ndarray:
    """Smith masking G1 = 1 / (1 + Lambda(mu)); 1 at normal incidence, 0 at grazing."""
    return np.where(np.asarray(mu) > 0, 1.0 / (1.0 + smith_lambda(mu, alpha)), 0.0)


def smith_g2(mu_in: np.ndarray, mu_out: np.ndarray, alpha: float) -> np.ndarray:
    """Height-correlated Smith masking-shadowing 1 / (1 + Lambda_in + Lambda_out) (Heitz 2014, eq. 99)."""
    g = 1.0 / (1.0 + smith_lambda(mu_in, alpha) + smith_lambda(mu_out, alpha))
    return np.where((np.asarray(mu_in) > 0) & (np.asarray(mu_out) > 0), g, 0.0)


def f0_from_ior(ior: float) -> float:
    """Fresnel reflectance at normal incidence ((ior - 1) / (ior + 1))^2."""
    return ((ior - 1.0) / (ior + 1.0)) ** 2


def fresnel_dielectric(cos_i: np.ndarray, ior: float) -> np.ndarray:
    """Exact unpolarized Fresnel reflectance of a dielectric (light from outside, relative ior > 0)."""
    c = np.clip(np.abs(np.asarray(cos_i, float)), 0.0, 1.0)
    g2 = ior * ior - 1.0 + c * c
    total = g2 < 0  # total internal reflection (ior < 1 only)
    g = np.sqrt(np.maximum(g2, 0.0))
    a = (g - c) / np.maximum(g + c, _EPS)
    b = (c * (g + c) - 1.0) / np.maximum(c * (g - c) + 1.0, _EPS)
    return np.where(total, 1.0, 0.5 * a * a * (1.0 + b * b))


def schlick_weight(cos_i: np.ndarray) -> np.ndarray:
    """(1 - cos)^5: Schlick's Fresnel is F0 + (1 - F0) times this."""
    return (1.0 - np.clip(np.asarray(cos_i, float), 0.0, 1.0)) ** 5


def sample_ggx_vndf(w_out: np.ndarray, alpha: float, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Microfacet normals h (..., 3) from the GGX distribution of normals visible from ``w_out``
    (local frame, normal +Z; Heitz 2018, "Sampling the GGX distribution of visible normals").

    ``w_out`` (..., 3) broadcasts against ``u1``, ``u2`` in [0, 1).  Density of h:
    G1(w_out) max(0, w_out.h) D(h) / mu_out; of the reflected w_in = 2 (w_out.h) h - w_out that
    density divided by 4 (w_out.h), so f_ss mu_in / pdf(w_in) = F G2 / G1(w_out).
    """
    v = np.asarray(w_out, float)
    vh = np.stack([alpha * v[..., 0], alpha * v[..., 1], v[..., 2]], axis=-1)
    vh = vh / np.linalg.norm(vh, axis=-1, keepdims=True)
    lensq = vh[..., 0] ** 2 + vh[..., 1] ** 2
    safe = np.sqrt(np.maximum(lensq, _EPS))
    t1 = np.where(
        (lensq > 1e-12)[..., None],
        np.stack([-vh[..., 1], vh[..., 0], np.zeros_like(lensq)], axis=-1) / safe[..., None],
        np.array([1.0, 0.0, 0.0]),
    )
    t2 = np.cross(vh, t1)
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + vh[..., 2])
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    p3 = np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    nh = p1[..., None] * t1 + p2[..., None] * t2 + p3[..., None] * vh
    h = np.stack([alpha * nh[..., 0], alpha * nh[..., 1], np.maximum(nh[..., 2], 0.0)], axis=-1)
    return h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), _EPS)


def ggx_lobe_cos(normal: np.ndarray, w_in: np.ndarray, w_out: np.ndarray, alpha: float):
    """The Fresnel-free single-scattering lobe times the cosine, D G2 / (4 mu_out) (N,), and
    w_out . h (N,) for the Fresnel term; zero unless both directions are above the surface."""
    n, wi, wo = (np.atleast_2d(np.asarray(a, float)) for a in (normal, w_in, w_out))
    mu_in = np.einsum("ij,ij->i", n, wi)
    mu_out = np.einsum("ij,ij->i", n, wo)
    h = wi + wo
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), _EPS)
    lobe = (
        ggx_distribution(np.einsum("ij,ij->i", n, h), alpha) * smith_g2(mu_in, mu_out, alpha) / (4.0 * np.maximum(mu_out, _EPS))
    )
    return np.where((mu_in > 0) & (mu_out > 0), lobe, 0.0), np.einsum("ij,ij->i", wo, h)


def microfacet_reflection(normal: np.ndarray, w_in: np.ndarray, w_out: np.ndarray, alpha: float, ior: float) -> np.ndarray:
    """Single-scattering GGX reflection F D G2 / (4 mu_in mu_out) (N,) with the exact dielectric
    Fresnel F(w_in . h): the reciprocal core of the specular lobe (no multiple-scattering factor)."""
    lobe, cos_oh = ggx_lobe_cos(normal, w_in, w_out, alpha)
    mu_in = np.einsum("ij,ij->i", np.atleast_2d(normal), np.atleast_2d(w_in))
    return fresnel_dielectric(cos_oh, ior) * lobe / np.maximum(mu_in, _EPS)


def unit_square_rule(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n x n tensor Gauss-Legendre rule on [0, 1)^2: (u1, u2, weights summing to 1)."""
    x, w = gauss_legendre(n, (0.0, 1.0))
    u1, u2 = np.meshgrid(x, x, indexing="ij")
    return u1.ravel(), u2.ravel(), np.outer(w, w).ravel()


# ------------------------------------------------------------------------------ directional albedo


@functools.lru_cache(maxsize=1)
def _mu_nodes() -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Legendre nodes and weights on [0, 1] the albedo tables use (cached, read-only:
    interpolate_mu is called per shading chunk)."""
    nodes, weights = gauss_legendre(_ALBEDO_NODES, (0.0, 1.0))
    nodes.flags.writeable = weights.flags.writeable = False
    return nodes, weights


@functools.lru_cache(maxsize=64)
def albedo_table(alpha: float, ior: float) -> np.ndarray:
    """Directional albedos of the single-scattering GGX lobe on the mu nodes (_mu_nodes):
    (3, n) rows E_1 (F = 1), E_5 (F = (1 - c)^5, Schlick's part) and E_d (F = dielectric(ior)).

    E_F(mu) = int F D G2 / (4 mu) dω_in = E_h~VNDF[F G2 / G1(mu)] by a tensor Gauss-Legendre rule
    on the VNDF's unit square (smooth integrand: < 1e-4 vs 96^2 points).  Cached, read-only.
    """
    mu, _ = _mu_nodes()
    u1, u2, w = unit_square_rule(_VNDF_GRID)
    s = np.sqrt(1.0 - mu * mu)
    wo = np.stack([s, np.zeros_like(mu), mu], axis=-1)[:, None, :]  # (n, 1, 3)
    h = sample_ggx_vndf(wo, alpha, u1[None, :], u2[None, :])  # (n, m, 3)
    c = np.einsum("nmk,nk->nm", h, wo[:, 0])  # w_out . h
    mu_in = 2.0 * c * h[..., 2] - mu[:, None]
    weight = smith_g2(mu_in, mu[:, None], alpha) / smith_g1(mu, alpha)[:, None] * w[None, :]
    table = np.stack([weight.sum(1), (weight * schlick_weight(c)).sum(1), (weight * fresnel_dielectric(c, ior)).sum(1)])
    table.flags.writeable = False
    return table


def interpolate_mu(values: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Values tabulated on the mu nodes, (n,) or (n, C), linearly interpolated at ``mu`` (N,)
    (clamped to [0, 1]) -> (N,) or (N, C)."""
    nodes, _ = _mu_nodes()
    x = np.clip(mu, 0.0, 1.0)
    if values.ndim == 1:
        return np.interp(x, nodes, values)
    if (values == values[:, :1]).all():  # grey (a dielectric's untinted tables): one interpolation
        return np.repeat(np.interp(x, nodes, values[:, 0])[:, None], values.shape[1], axis=1)
    return np.stack([np.interp(x, nodes, values[:, c]) for c in range(values.shape[1])], axis=-1)


def hemispherical_average(values: np.ndarray) -> float:
    """2 int_0^1 g(mu) mu dmu of a function tabulated on the mu nodes (cosine-weighted average)."""
    mu, w = _mu_nodes()
    return float(2.0 * np.sum(values * mu * w))


def energy_compensation(e_single: np.ndarray, e_avg: float, fss: np.ndarray) -> np.ndarray:
    """Kulla-Conty multiple-scattering factor 1 + Fms (1 - E) / E with Fms = Fss E_avg / (1 - Fss (1 - E_avg))
    (Cycles' microfacet_ggx_preserve_energy).  ``e_single`` (n,), ``fss`` (3,) or (n, 3) -> (n, 3)."""
    fss = np.asarray(fss, float)
    fms = fss * e_avg / (1.0 - fss * (1.0 - e_avg))
    e = np.maximum(np.asarray(e_single, float), _EPS)
    return 1.0 + fms * ((1.0 - e) / e)[..., None]


# ------------------------------------------------------------------------------------ the material


@dataclass(frozen=True)
class Principled:
    """Blender's Principled BSDF (v2) / glTF metallic-roughness, uniform parameters.

    ``base_color`` (3,) linear in [0, 1]; ``roughness`` perceptual in (0, 1]; ``metallic`` in
    [0, 1]; ``ior`` >= 1; ``specular_tint`` (3,) in [0, 1].  Per-vertex base colours are passed
    to the methods as arrays (N, 3) instead.
    """

    base_color: tuple = (0.8, 0.8, 0.8)
    roughness: float = 0.5
    metallic: float = 0.0
    ior: float = 1.5
    specular_tint: tuple = (1.0, 1.0, 1.0)
    _tables: dict = field(init=False, repr=False, compare=False, hash=False, default=None)

    def __post_init__(self) -> None:
        alpha = self.alpha
        e1, e5, ed = albedo_table(alpha, float(self.ior))
        tint = np.asarray(self.specular_tint, float)
        f0t = f0_from_ior(self.ior) * tint
        f0 = f0_from_ior(self.ior)
        # tinted dielectric F = F0t + (1 - F0t) (F_real - F0) / (1 - F0): linear in F_real
        scale = (1.0 - f0t) / (1.0 - f0)
        offset = f0t - scale * f0
        e_diel = offset[None, :] * e1[:, None] + scale[None, :] * ed[:, None]  # (n, 3)
        e_avg = hemispherical_average(e1)
        mu, _ = _mu_nodes()
        fss_diel = offset + scale * hemispherical_average(fresnel_dielectric(mu, float(self.ior)))
        comp_diel = energy_compensation(e1, e_avg, fss_diel)
        object.__setattr__(
            self,
            "_tables",
            {
                "e1": e1,
                "e5": e5,
                "e_avg": e_avg,
                "offset": offset,
                "scale": scale,
                "spec_albedo": comp_diel * e_diel,  # (n, 3)
                "comp_diel": comp_diel,
            },
        )

    @property
    def alpha(self) -> float:
        return max(float(self.roughness), MIN_ROUGHNESS) ** 2

    # -- per-view weights -------------------------------------------------------------------
    def base(self, base_color: np.ndarray | None, n: int) -> np.ndarray:
        if base_color is None:
            return np.broadcast_to(np.asarray(self.base_color, float), (n, 3))
        return np.asarray(base_color, float)

    def specular_albedo(self, mu_out: np.ndarray) -> np.ndarray:
        """Directional albedo (N, 3) of the dielectric specular layer (multiple scattering included)."""
        return interpolate_mu(self._tables["spec_albedo"], mu_out)

    def diffuse_weight(self, mu_out: np.ndarray, base_color: np.ndarray | None = None) -> np.ndarray:
        """Lambertian reflectance seen from mu_out (N, 3): (1 - m)(1 - max_rgb A_spec(mu_out)) base;
        the diffuse radiance is this / pi times the irradiance."""
        mu_out = np.asarray(mu_out, float)
        layer = np.clip(1.0 - self.specular_albedo(mu_out).max(axis=1), 0.0, 1.0)
        return (1.0 - self.metallic) * layer[:, None] * self.base(base_color, mu_out.shape[0])

    def _compensation(self, mu_out: np.ndarray, fss: np.ndarray) -> np.ndarray:
        e1 = interpolate_mu(self._tables["e1"], mu_out)
        return energy_compensation(e1, self._tables["e_avg"], fss)

    def specular_fresnel(self, cos_oh: np.ndarray, mu_out: np.ndarray, base_color: np.ndarray | None = None) -> np.ndarray:
        """F times the multiple-scattering factor and the metallic mix, per pair (N, 3):
        the specular f = this * D G2 / (4 mu_in mu_out).  ``cos_oh`` (N,) with ``mu_out`` (N,) and
        ``base_color`` (N, 3) per pair, or (N, S) for S pairs per point with them per point (N,),
        (N, 3) -> (N, S, 3): the per-point factors are computed once, not per pair."""
        cos_oh = np.asarray(cos_oh, float)
        n = cos_oh.shape[0]
        per = (slice(None),) + (None,) * (cos_oh.ndim - 1)  # a point's factor over its pairs
        t = self._tables
        f_real = fresnel_dielectric(cos_oh, float(self.ior))
        f_diel = t["offset"] + t["scale"] * f_real[..., None]
        out = (1.0 - self.metallic) * f_diel * interpolate_mu(t["comp_diel"], mu_out)[per]
        if self.metallic > 0:
            f0 = self.base(base_color, n)
            fss = f0 + (1.0 - f0) / 21.0  # 2 int (F0 + (1 - F0)(1 - mu)^5) mu dmu
            comp = self._compensation(mu_out, fss)
            out = out + self.metallic * (f0[per] + (1.0 - f0[per]) * schlick_weight(cos_oh)[..., None]) * comp[per]
        return out

    def metal_albedo(self, mu_out: np.ndarray, base_color: np.ndarray | None = None) -> np.ndarray:
        """Directional albedo (N, 3) of the metallic lobe (multiple scattering included)."""
        mu_out = np.asarray(mu_out, float)
        f0 = self.base(base_color, mu_out.shape[0])
        e1 = interpolate_mu(self._tables["e1"], mu_out)[:, None]
        e5 = interpolate_mu(self._tables["e5"], mu_out)[:, None]
        return (f0 * e1 + (1.0 - f0) * e5) * self._compensation(mu_out, f0 + (1.0 - f0) / 21.0)

    def albedo(self, mu_out: np.ndarray, base_color: np.ndarray | None = None) -> np.ndarray:
        """Total directional albedo (N, 3) of the material seen from mu_out (white furnace)."""
        mu_out = np.asarray(mu_out, float)
        return (
            (1.0 - self.metallic) * self.specular_albedo(mu_out)
            + self.diffuse_weight(mu_out, base_color)
            + self.metallic * self.metal_albedo(mu_out, base_color)
        )

    # -- pointwise evaluation ---------------------------------------------------------------
    def eval_cos(
        self, normal: np.ndarray, w_in: np.ndarray, w_out: np.ndarray, base_color: np.ndarray | None = None
    ) -> np.ndarray:
        """f(w_in, w_out) max(0, n.w_in) per row (N, 3): what the reflection equation integrates."""
        n, wi, wo = (np.atleast_2d(np.asarray(a, float)) for a in (normal, w_in, w_out))
        mu_in = np.einsum("ij,ij->i", n, wi)
        mu_out = np.einsum("ij,ij->i", n, wo)
        front = (mu_in > 0) & (mu_out > 0)
        lobe, cos_oh = ggx_lobe_cos(n, wi, wo, self.alpha)
        diffuse = self.diffuse_weight(mu_out, base_color)
        spec = self.specular_fresnel(cos_oh, mu_out, base_color) * lobe[:, None]
        value = diffuse * (np.maximum(mu_in, 0.0) / np.pi)[:, None] + spec
        return np.where(front[:, None], value, 0.0)


def brdf_from_material(material: "Principled | None", base_color) -> Brdf:
    """The Brdf of a material (None: Lambert) with a uniform base colour (3,)."""
    if material is None:
        return Brdf("lambert", albedo=base_color)
    return Brdf(
        "principled",
        base_color=base_color,
        roughness=material.roughness,
        metallic=material.metallic,
        ior=material.ior,
        specular_tint=material.specular_tint,
    )


def material_from_brdf(brdf: Brdf) -> Principled | None:
    """The Principled evaluator of a principled Brdf; None for any other model (Lambert and the
    seed's lobes are evaluated by their callers): brdf_from_material's inverse."""
    if brdf.model != "principled":
        return None
    return Principled(
        base_color=brdf.base_color,
        roughness=brdf.roughness,
        metallic=brdf.metallic,
        ior=brdf.ior,
        specular_tint=brdf.specular_tint,
    )
