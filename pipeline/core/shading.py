"""The reflection equation's pieces that do not cast rays (pure NumPy): the principled material's
diffuse layer, importance samples of its specular lobe and their sum, a prefiltered environment
pyramid, and the lobe over discrete directions.  The renderer (pixels), the fit's transfer
(pipeline.core.prt, samples) and the report's sphere preview (sphere_radiance) shade through them.

The renderer (pipeline.core.render) integrates

    B(x, w_o) = int L(w) V(x, w) f(w, w_o) max(0, n.w) dω

as  diffuse  (over the light set's directions, exact solid angles)  +  specular:
* the bright pixels of the map (sun disks, lamps) evaluated exactly, pair by pair;
* the remainder of the map by *filtered importance sampling* (Krivanek & Colbert 2008): S samples
  of the GGX distribution of visible normals per point (Heitz 2018), each reading the remainder
  map prefiltered to the sample's solid angle 1 / (S pdf) from a box pyramid.  The estimator
  f cos / pdf = F G2 / G1(w_o) is exact per sample; the prefilter only trades noise for a blur
  at the scale of the sample spacing, which is below the lobe's own width.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from pipeline.core.envmap import downsample
from pipeline.core.material import Principled, ggx_distribution, ggx_lobe_cos, sample_ggx_vndf, smith_g1, smith_g2
from pipeline.core.sh import sh_evaluate
from pipeline.core.threads import thread_map
from pipeline.core.transfer import irradiance_from_sh

_EPS = 1e-12


def tangent_frames(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal tangents (t, b) (N, 3) with (t, b, n) right-handed (Duff et al. 2017)."""
    n = np.asarray(normal, float)
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    bt = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, bt


def front_cos(normal: np.ndarray, mu_out: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """max(0, n . w_j) for points (P, 3) seen from the front (mu_out = n . w_o > 0; 0 otherwise)
    and directions (D, 3): (P, D), the cosine the reflection equation integrates."""
    return np.where(np.asarray(mu_out)[:, None] > 0, np.maximum(np.asarray(normal) @ np.asarray(dirs).T, 0.0), 0.0)


def stratified_unit_square(count: int, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """(count, S, 2) points in [0, 1)^2: an n x n grid of cell centres (S = n^2 ~ ``n_samples``) with one
    random (Cranley-Patterson) shift per row, so that neighbouring points' errors are uncorrelated."""
    side = max(1, int(round(np.sqrt(n_samples))))
    grid = (np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2) + 0.5) / side
    return np.mod(grid[None] + rng.random((count, 1, 2)), 1.0)


@dataclass(frozen=True)
class EnvPyramid:
    """An (H, 2H, 3) equirect map and its 2x box-filtered (energy-preserving) levels down to height 2."""

    levels: tuple

    @classmethod
    def build(cls, env: np.ndarray) -> "EnvPyramid":
        levels = [np.asarray(env, float)]
        while levels[-1].shape[0] % 2 == 0 and levels[-1].shape[0] > 2:
            levels.append(downsample(levels[-1], 2))
        return cls(tuple(levels))

    def _bilinear(self, level: int, dirs: np.ndarray) -> np.ndarray:
        env = self.levels[level]
        h, w = env.shape[:2]
        theta = np.arccos(np.clip(dirs[:, 2], -1.0, 1.0))
        phi = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2.0 * np.pi)
        y = theta / np.pi * h - 0.5  # pixel centres at (i + 0.5): DESIGN.md equirect convention
        x = phi / (2.0 * np.pi) * w - 0.5
        y0 = np.floor(y)
        x0 = np.floor(x)
        fy = (y - y0)[:, None]
        fx = (x - x0)[:, None]
        r0 = np.clip(y0.astype(np.int64), 0, h - 1)
        r1 = np.clip(y0.astype(np.int64) + 1, 0, h - 1)
        c0 = np.mod(x0.astype(np.int64), w)
        c1 = np.mod(c0 + 1, w)
        return (1 - fy) * ((1 - fx) * env[r0, c0] + fx * env[r0, c1]) + fy * ((1 - fx) * env[r1, c0] + fx * env[r1, c1])

    def lookup(self, dirs: np.ndarray, solid_angle: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) in directions (N, 3) averaged over about ``solid_angle`` (N,) sr
        (trilinear: bilinear per level, linear between the two levels around the footprint)."""
        dirs = np.asarray(dirs, float)
        texel = (np.pi / self.levels[0].shape[0]) ** 2
        level = np.clip(0.5 * np.log2(np.maximum(solid_angle, _EPS) / texel), 0.0, len(self.levels) - 1)
        lo = np.floor(level).astype(np.int64)
        frac = (level - lo)[:, None]
        out = np.zeros((dirs.shape[0], 3))
        for k in np.unique(lo):
            sel = lo == k
            a = self._bilinear(int(k), dirs[sel])
            if k + 1 < len(self.levels):
                a = (1 - frac[sel]) * a + frac[sel] * self._bilinear(int(k) + 1, dirs[sel])
            out[sel] = a
        return out


@dataclass(frozen=True)
class LobeSamples:
    """Importance samples of the specular lobe for P points, S per point.

    directions (P, S, 3) world w_in; weight (P, S, 3) = f cos / pdf / S (F, multiple scattering,
    metallic mix included; zero below the horizon); solid_angle (P, S) = 1 / (S pdf).
    """

    directions: np.ndarray
    weight: np.ndarray
    solid_angle: np.ndarray


def specular_samples(
    material: Principled,
    normal: np.ndarray,
    view_dir: np.ndarray,
    n_samples: int,
    rng: np.random.Generator,
    base_color: np.ndarray | None = None,
) -> LobeSamples:
    """GGX VNDF samples of the principled specular lobe at points with unit normals and view
    directions (P, 3), on a stratified pattern (stratified_unit_square)."""
    n = np.asarray(normal, float)
    v = np.asarray(view_dir, float)
    p = n.shape[0]
    u = stratified_unit_square(p, n_samples, rng)
    t, b = tangent_frames(n)
    mu_out = np.clip(np.einsum("pk,pk->p", n, v), 1e-4, 1.0)
    v_local = np.stack([np.einsum("pk,pk->p", t, v), np.einsum("pk,pk->p", b, v), mu_out], axis=1)
    v_local /= np.linalg.norm(v_local, axis=1, keepdims=True)
    alpha = material.alpha
    h = sample_ggx_vndf(v_local[:, None, :], alpha, u[..., 0], u[..., 1])  # (P, S, 3)
    c = np.einsum("psk,pk->ps", h, v_local)
    w_local = 2.0 * c[..., None] * h - v_local[:, None, :]
    mu_in = w_local[..., 2]
    dirs = w_local[..., 0:1] * t[:, None] + w_local[..., 1:2] * b[:, None] + w_local[..., 2:3] * n[:, None]
    s = u.shape[1]
    g1 = smith_g1(mu_out, alpha)[:, None]
    ratio = np.where(mu_in > 0, smith_g2(mu_in, mu_out[:, None], alpha) / g1, 0.0) / s
    fres = material.specular_fresnel(np.clip(c, 0, 1), mu_out, None if base_color is None else np.asarray(base_color, float))
    pdf = g1 * ggx_distribution(h[..., 2], alpha) / (4.0 * mu_out[:, None])
    return LobeSamples(dirs, fres * ratio[..., None], 1.0 / (s * np.maximum(pdf, _EPS)))


def diffuse_layer(material: Principled | None, mu_out: np.ndarray) -> np.ndarray:
    """kd(mu_o) (N, 3): the base colour's weight in the diffuse reflectance (1 for Lambert); the
    diffuse radiance is base colour x kd / pi x irradiance."""
    if material is None:
        return np.ones((np.asarray(mu_out).shape[0], 3))
    return material.diffuse_weight(np.clip(mu_out, 0.0, 1.0), np.ones((np.asarray(mu_out).shape[0], 3)))


def sampled_lobe(
    material: Principled,
    normal: np.ndarray,
    view_dir: np.ndarray,
    n_samples: int,
    rng: np.random.Generator,
    seen,
    base_color: np.ndarray | None = None,
) -> np.ndarray:
    """The specular lobe by importance sampling (P, 3): sum_s w_s L_s over specular_samples' S
    samples per point (S is ``n_samples`` rounded to a square), where ``seen(directions (M, 3),
    solid_angles (M,), points (M,))`` gives the radiance L (M, 3) arriving along the M samples of
    non-zero weight (``points``: each sample's point, 0..P-1); the other samples see nothing."""
    samples = specular_samples(material, normal, view_dir, n_samples, rng, base_color)
    q, ns = samples.directions.shape[:2]
    dirs = samples.directions.reshape(-1, 3)
    live = np.flatnonzero(samples.weight.reshape(-1, 3).max(axis=1) > 0)
    radiance = np.zeros((q * ns, 3))
    radiance[live] = seen(dirs[live], samples.solid_angle.reshape(-1)[live], live // ns)
    return np.einsum("psc,psc->pc", samples.weight, radiance.reshape(q, ns, 3))


def sphere_radiance(
    material: Principled | None,
    coeffs: np.ndarray,
    normal: np.ndarray,
    view_dir: np.ndarray,
    base_color: np.ndarray,
    n_samples: int = 64,
    seed: int = 0,
) -> np.ndarray:
    """Radiance (P, 3) of a convex object (a sphere: no shadows, no interreflection) under SH lighting
    ``coeffs`` at unit normals and view directions (P, 3), with the renderer's shading
    (Renderer.shade_parts): base colour x diffuse_layer / pi x the irradiance (exact, from the SH) plus
    the lobe by sampled_lobe (``n_samples`` per point) reading the lighting, clamped at 0, along each
    sample.  The report's sphere preview."""
    n = np.asarray(normal, float)
    v = np.asarray(view_dir, float)
    mu_out = np.einsum("pc,pc->p", n, v)
    out = np.asarray(base_color, float) * diffuse_layer(material, mu_out) / np.pi * irradiance_from_sh(coeffs, n)
    if material is None:
        return out

    def seen(dirs: np.ndarray, solid_angle: np.ndarray, points: np.ndarray) -> np.ndarray:
        return np.maximum(sh_evaluate(coeffs, dirs), 0.0)

    return out + sampled_lobe(material, n, v, n_samples, np.random.default_rng(seed), seen)


def specular_over_directions(
    material: Principled,
    normal: np.ndarray,
    view_dir: np.ndarray,
    dirs: np.ndarray,
    power: np.ndarray,
    visibility: np.ndarray | None,
    cut_cos: float,
    base_color: np.ndarray | None = None,
) -> np.ndarray:
    """Specular radiance (P, 3) from discrete directions (D, 3) of power L dω (D, 3):
    sum_j power_j V_pj f_spec(w_j, w_o) max(0, n.w_j), evaluated only on the pairs whose w_j is
    within the lobe's support (cos to the mirror direction > ``cut_cos``)."""
    n = np.asarray(normal, float)
    v = np.asarray(view_dir, float)
    pi, di, vis = _lobe_pairs(n, v, dirs, visibility, cut_cos)
    return _lobe_sum(material, n, v, dirs, power, pi, di, vis, base_color)


FOOTPRINT_SHARPNESS = 0.25  # a footprint whose mirror directions spread less than this x alpha (rad) is shaded
# at its mean: a box of width s over a lobe of width w changes it by ~ s^2 / 24 w^2


def specular_over_footprint(
    material: Principled,
    normals: np.ndarray,
    view_dirs: np.ndarray,
    dirs: np.ndarray,
    power: np.ndarray,
    visibility: np.ndarray | None,
    cut_cos: float,
    base_color: np.ndarray | None = None,
) -> np.ndarray:
    """specular_over_directions (P, 3) averaged over each point's pixel footprint: ``normals`` and
    ``view_dirs`` (P, K, 3) at K points of the surface one pixel sees (pipeline.raycast
    .pixel_footprints), ``visibility`` (P, D) shared by them.  A highlight of a small source a few
    pixels wide is the lobe averaged over the pixel, not the lobe at its centre: at the centre only,
    the Cycles night sphere's highlights fit roughness 0.17 for 0.15 under the true lighting.
    The pairs are found once, around the footprint's mean mirror direction with the support
    widened by the footprint's own spread of mirror directions; a footprint narrow against the
    lobe (FOOTPRINT_SHARPNESS) and on one side of the horizon is shaded once, at its mean normal
    and view direction."""
    n = np.asarray(normals, float)
    v = np.asarray(view_dirs, float)
    k = n.shape[1]
    mirror = 2.0 * np.einsum("pkc,pkc->pk", n, v)[..., None] * n - v  # (P, K, 3)
    mean = mirror.sum(axis=1)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    spread = np.arccos(np.clip(np.einsum("pkc,pc->pk", mirror, mean).min(axis=1), -1.0, 1.0))  # (P,)
    out = np.zeros((n.shape[0], 3))
    front = np.einsum("pkc,pkc->pk", n, v) > 0
    small = (spread <= FOOTPRINT_SHARPNESS * material.alpha) & (front.all(axis=1) | ~front.any(axis=1))
    narrow = np.flatnonzero(small)
    if narrow.size:
        n0, v0 = (a[narrow].sum(axis=1) for a in (n, v))
        n0, v0 = (a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12) for a in (n0, v0))
        out[narrow] = specular_over_directions(
            material,
            n0,
            v0,
            dirs,
            power,
            None if visibility is None else visibility[narrow],
            cut_cos,
            None if base_color is None else np.asarray(base_color)[narrow],
        )
    wide = np.flatnonzero(~small)
    if wide.size == 0:
        return out
    widened = np.cos(np.minimum(np.pi, np.arccos(np.clip(cut_cos, -1.0, 1.0)) + spread[wide]))
    pi, di = np.nonzero(mean[wide] @ dirs.T > widened[:, None])
    pi, di, vis = _visible_pairs(pi, di, None if visibility is None else visibility[wide])
    base = None if base_color is None else np.asarray(base_color)[wide]
    out[wide] = sum(_lobe_sum(material, n[wide, i], v[wide, i], dirs, power, pi, di, vis, base) for i in range(k)) / k
    return out


def _lobe_pairs(n: np.ndarray, v: np.ndarray, dirs: np.ndarray, visibility: np.ndarray | None, cut_cos: float):
    """(point ids, direction ids, their visibility or None) of the pairs within the lobe's support."""
    mu_out, r = _mirror(n, v)
    return _visible_pairs(*_support_pairs(n, mu_out, r, dirs, cut_cos), visibility)


def _mirror(n: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n . v (P,), the mirror directions 2 (n . v) n - v (P, 3)) of unit normals and view directions."""
    mu_out = np.einsum("pk,pk->p", n, v)
    return mu_out, 2.0 * mu_out[:, None] * n - v


def _support_pairs(
    n: np.ndarray, mu_out: np.ndarray, r: np.ndarray, dirs: np.ndarray, cut_cos: float
) -> tuple[np.ndarray, np.ndarray]:
    """(point ids, direction ids) of the pairs within the lobe's support (_mirror's mu_out and r)."""
    return np.nonzero((r @ dirs.T > cut_cos) & (n @ dirs.T > 0) & (mu_out[:, None] > 0))


def _visible_pairs(pi: np.ndarray, di: np.ndarray, visibility: np.ndarray | None):
    """The pairs (point ids, direction ids) whose visibility (P, D) bool or weights in [0, 1] is
    positive, with that visibility (None when there is none)."""
    if visibility is None:
        return pi, di, None
    vis = visibility[pi, di]
    keep = vis > 0
    return pi[keep], di[keep], vis[keep]


def _lobe_sum(
    material: Principled,
    n: np.ndarray,
    v: np.ndarray,
    dirs: np.ndarray,
    power: np.ndarray,
    pi: np.ndarray,
    di: np.ndarray,
    vis: np.ndarray | None,
    base_color: np.ndarray | None,
) -> np.ndarray:
    """sum over the pairs (pi, di) of power V f_spec max(0, n.w) per point (P, 3); pairs with
    either direction below the surface give 0 (ggx_lobe_cos)."""
    out = np.zeros((n.shape[0], 3))
    if pi.size == 0:
        return out
    contrib = _pair_radiance(material, n, v, dirs, power, pi, di, vis, base_color)
    for c in range(3):
        out[:, c] = np.bincount(pi, weights=contrib[:, c], minlength=n.shape[0])
    return out


def _pair_radiance(
    material: Principled,
    n: np.ndarray,
    v: np.ndarray,
    dirs: np.ndarray,
    power: np.ndarray,
    pi: np.ndarray,
    di: np.ndarray,
    vis: np.ndarray | None,
    base_color: np.ndarray | None,
) -> np.ndarray:
    """power V f_spec max(0, n.w) of each pair (pi, di) (pairs, 3) (_lobe_sum's terms)."""
    mu_out = np.clip(np.einsum("pk,pk->p", n[pi], v[pi]), 0.0, 1.0)
    lobe, cos_oh = ggx_lobe_cos(n[pi], dirs[di], v[pi], material.alpha)
    if vis is not None and vis.dtype != bool:
        lobe = lobe * vis
    fres = material.specular_fresnel(cos_oh, mu_out, None if base_color is None else np.asarray(base_color, float)[pi])
    return fres * (lobe[:, None] * power[di])


def specular_columns(
    material: Principled,
    normal: np.ndarray,
    view_dir: np.ndarray,
    dirs: np.ndarray,
    visibility: np.ndarray | None,
    cut_cos: float,
    base_color: np.ndarray | None = None,
) -> np.ndarray:
    """specular_over_directions of each direction (D, 3) alone at unit power (P, D, 3), with
    ``visibility`` (P, D): each direction's pairs found as that function finds them (so the
    columns are its answers to the bit), all pairs evaluated in one pass."""
    n = np.asarray(normal, float)
    v = np.asarray(view_dir, float)
    mu_out, r = _mirror(n, v)
    found = []
    for j in range(dirs.shape[0]):
        pi, _ = _support_pairs(n, mu_out, r, dirs[j : j + 1], cut_cos)
        pi, _, vis = _visible_pairs(pi, np.zeros_like(pi), None if visibility is None else visibility[:, j : j + 1])
        found.append((pi, np.full(pi.size, j), vis))
    pi, di = (np.concatenate([f[k] for f in found]) for k in (0, 1))
    vis = None if visibility is None else np.concatenate([f[2] for f in found])
    out = np.zeros((n.shape[0], dirs.shape[0], 3))
    power = np.ones((dirs.shape[0], 3))

    def part(s: slice) -> None:
        out[pi[s], di[s]] = _pair_radiance(material, n, v, dirs, power, pi[s], di[s], None if vis is None else vis[s], base_color)

    step = max(1 << 16, -(-pi.size // (os.cpu_count() or 1)))  # the pairs in a part per core
    thread_map(part, [slice(a, a + step) for a in range(0, pi.size, step)])
    return out


def lobe_support_cos(alpha: float, fraction: float = 1e-4) -> float:
    """cos of the angle from the mirror direction beyond which the GGX lobe is below ``fraction``
    of its peak: D(h) / D(n) < fraction when tan^2 theta_h > alpha^2 (fraction^-1/2 - 1); the
    reflected direction moves by twice theta_h (plus margin for the off-specular stretch)."""
    tan2 = alpha * alpha * (fraction**-0.5 - 1.0)
    theta_h = np.arctan(np.sqrt(tan2))
    return float(np.cos(min(np.pi, 2.5 * theta_h)))
