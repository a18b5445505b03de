"""The frequency-space renderer of the seed's convex lobes (R&H 2001): a lighting prepared for one
BRDF — irradiance from SH (the clamped-cosine filter) and the lobe's lighting filtered in SH, or, for
a lobe sharper than the SH bands afford, prefiltered in the angular domain (a circular convolution
per row pair of an equirect map) — evaluated at normals and view directions (pure NumPy).

Conventions: DESIGN.md's equirect maps and real SH; filters A_l per band (pipeline.core.forward);
lighting radiance in the photos' linear units.  Used by relight's frequency method, its angular
method for lobes sharper than its cells, and the report's sphere previews.
"""

from __future__ import annotations

import numpy as np

from pipeline.core import forward
from pipeline.core.brdf import Brdf, reflect
from pipeline.core.envmap import bilinear_lookup, downsample, equirect_angles, equirect_solid_angles
from pipeline.core.sh import num_coeffs, order_of, project_envmap
from pipeline.core.transfer import irradiance_from_sh

DIFFUSE_ORDER = 16  # |Â_l| beyond l = 16 is < 0.15% of Â_0: irradiance of an env map to that level
LOBE_CUTOFF = 1e-3  # a lobe "needs" band l while |A_l| > LOBE_CUTOFF * A_0
MAX_LOBE_ORDER = 400  # the filter is examined up to this band


def brdf_lobe_filter(brdf: Brdf, order: int) -> np.ndarray:
    """A_l for l = 0..order of the BRDF's specular lobe (pipeline.core.forward); zeros without one."""
    if not brdf.has_lobe:
        return np.zeros(order + 1)
    return np.asarray(forward.specular_lobe_filter(brdf.model, brdf.lobe_width, order), float)


def needed_order(filt: np.ndarray) -> int:
    """Smallest L with |A_l| <= LOBE_CUTOFF * A_0 for every l > L (len(filt)-1 when it never decays)."""
    filt = np.abs(np.asarray(filt, float))
    if filt[0] <= 0:
        return 0
    above = np.nonzero(filt > LOBE_CUTOFF * filt[0])[0]
    return int(above[-1]) if above.size else 0


def lobe_kernel(filt: np.ndarray, cos_gamma: np.ndarray) -> np.ndarray:
    """Angular kernel K(cos gamma) = sum_l (2l+1)/(4 pi) A_l P_l(cos gamma) (Funk-Hecke inverse)."""
    l = np.arange(len(filt))
    return np.polynomial.legendre.legval(np.clip(cos_gamma, -1.0, 1.0), (2 * l + 1) / (4 * np.pi) * filt)


def prefilter_envmap(env: np.ndarray, filt: np.ndarray, height: int) -> np.ndarray:
    """The equirect map convolved with the radial lobe of filter ``filt``: P(r) = ∫ L(w) K(r.w) dw.

    Output (h, 2h, 3) with h = the largest divisor of the map height <= ``height``.  Input and
    output share the azimuth grid, so for each pair of rows the sum over azimuth is a circular
    convolution (one FFT per row pair).  The discrete kernel is normalized to integrate to A_0, so
    a lobe narrower than a pixel still conserves energy.
    """
    h_in = env.shape[0]
    factor = max(1, h_in // height)
    while h_in % factor:
        factor -= 1
    env = downsample(np.asarray(env, float), factor)
    h, w = env.shape[:2]
    theta, phi = equirect_angles(h)
    omega = equirect_solid_angles(h)
    # kernel tabulated in angle (fine enough for the sharpest lobe we prefilter), then interpolated
    gamma_table = np.linspace(0.0, np.pi, 8192)
    k_table = lobe_kernel(filt, np.cos(gamma_table))
    dphi = phi - phi[0]
    st, ct = np.sin(theta), np.cos(theta)
    out = np.empty((h, w, 3))
    spectrum = np.fft.rfft(env * omega[:, None, None], axis=1)  # (h, F, 3)
    for i in range(h):
        cos_gamma = ct[i] * ct[:, None] + st[i] * st[:, None] * np.cos(dphi)[None, :]  # (h', W)
        kern = np.interp(np.arccos(np.clip(cos_gamma, -1, 1)), gamma_table, k_table)
        norm = float((kern * omega[:, None]).sum())
        kern_f = np.fft.rfft(kern, axis=1)  # (h', F)
        row = np.fft.irfft(np.einsum("if,ifc->fc", kern_f, spectrum), n=w, axis=0)
        out[i] = row * (filt[0] / norm if norm > 0 else 0.0)
    return out


class Lighting:
    """New lighting prepared for one BRDF: the irradiance SH and the lobe-filtered lighting (SH or maps).

    Give ``coeffs`` (SH lighting, ((L+1)^2, 3)) or ``env`` (an equirect map (H, 2H, 3)).  SH
    lighting is band-limited, so the filtered sums are exact to its order; an env map is
    projected to the bands the lobe needs, or prefiltered in the angular domain for sharp lobes.
    The lobe filter is the forward model's per-sample one (forward.sample_lobe_filters: Phong's is
    fixed, the microfacet one depends on n.v, tabulated on forward.VIEW_COS_GRID); sharp
    view-dependent lobes get one prefiltered map per grid entry, interpolated like the filters.
    """

    def __init__(
        self,
        brdf: Brdf,
        *,
        coeffs: np.ndarray | None = None,
        env: np.ndarray | None = None,
        lobe_sh_order: int = 24,
        prefilter_height: int = 128,
        source: str = "",
    ):
        self.source = source
        self.brdf = brdf
        lobe_order = needed_order(brdf_lobe_filter(brdf, MAX_LOBE_ORDER))
        self.prefiltered: list[np.ndarray] | None = None
        if coeffs is not None:
            coeffs = np.asarray(coeffs, float)
            order = order_of(coeffs.shape[0])
            self.kind = "sh"
        else:
            sharp = lobe_order > lobe_sh_order
            order = max(DIFFUSE_ORDER, 0 if sharp else lobe_order)
            coeffs = project_envmap(env, order)
            if sharp:
                self.prefiltered = [prefilter_envmap(env, filt, prefilter_height) for filt in self._grid_filters(lobe_order)]
            self.kind = "envmap"
        self.order = order
        d_order = min(order, DIFFUSE_ORDER) if self.kind == "envmap" else order
        self.diffuse_lighting = coeffs[: num_coeffs(d_order)]
        self.lobe_lighting = coeffs if lobe_order > 0 and self.prefiltered is None else None
        self.lobe_order = lobe_order

    def _width(self) -> tuple[str, float]:
        return self.brdf.model, self.brdf.lobe_width

    def _grid_filters(self, order: int) -> np.ndarray:
        """The lobe's filters on forward.VIEW_COS_GRID (one row for a view-independent lobe)."""
        model, width = self._width()
        if model == "phong":
            return np.asarray(forward.specular_lobe_filter(model, width, order), float)[None, :]
        return np.asarray(forward.sample_lobe_filters(model, width, order, forward.VIEW_COS_GRID), float)

    def describe(self) -> dict:
        return {
            "path": self.source,
            "kind": self.kind,
            "sh_order": self.order,
            "lobe_bands": self.lobe_order,
            "lobe": "none" if self.lobe_order == 0 else ("prefiltered map" if self.prefiltered is not None else "sh"),
        }

    def _filtered_lobe(self, r: np.ndarray, cos_view: np.ndarray, chunk: int = 8192) -> np.ndarray:
        """sum_l A_l(n.v) sum_m L_lm Y_lm(r) per sample (N, 3)."""
        if self.prefiltered is not None:
            if len(self.prefiltered) == 1:
                return bilinear_lookup(self.prefiltered[0], r)
            grid = forward.VIEW_COS_GRID
            x = np.clip(cos_view, grid[0], grid[-1])
            pos = (x - grid[0]) / (grid[1] - grid[0])
            i = np.minimum(pos.astype(np.int64), len(grid) - 2)
            frac = (pos - i)[:, None]
            out = np.zeros((len(r), 3))
            for j in np.unique(i):
                sel = i == j
                out[sel] = (1 - frac[sel]) * bilinear_lookup(self.prefiltered[j], r[sel]) + frac[sel] * bilinear_lookup(
                    self.prefiltered[j + 1], r[sel]
                )
            return out
        model, width = self._width()
        out = np.empty((len(r), 3))
        for s in range(0, len(r), chunk):
            bands = forward.band_projections(self.lobe_lighting, r[s : s + chunk])  # (n, L+1, 3)
            filt = forward.sample_lobe_filters(model, width, self.order, cos_view[s : s + chunk])  # (n, L+1)
            out[s : s + chunk] = np.einsum("nl,nlc->nc", filt, bands)
        return out

    def prepare(self) -> "Lighting":
        """Nothing is cached lazily here: shade_hits may run in threads as it is."""
        return self

    def radiance(self, normal: np.ndarray, view_dir: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """Outgoing radiance (N, 3) at unit normals and unit directions to the viewer (N, 3).

        The forward model of pipeline.core.forward (diffuse + lobe factor k_c times the filtered
        lighting at r); ``albedo`` (N, 3) or (3,) replaces the BRDF's uniform albedo (textures).
        """
        out = np.asarray(albedo, float) / np.pi * irradiance_from_sh(self.diffuse_lighting, normal)
        if self.lobe_order > 0:
            r = reflect(view_dir, normal)
            r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
            cos_view = np.einsum("ij,ij->i", normal, view_dir)
            k = forward.lobe_factor(self.brdf, forward.fresnel_grazing(normal, view_dir))
            out = out + np.where((cos_view > 0)[:, None], k * self._filtered_lobe(r, cos_view), 0.0)
        return np.maximum(out, 0.0)

    def shade_hits(
        self, tri: np.ndarray, bary: np.ndarray, normal: np.ndarray, view_dir: np.ndarray, albedo: np.ndarray
    ) -> np.ndarray:
        """Radiance (N, 3) at ray hits (face ids, barycentrics, interpolated normals, view directions, albedo)."""
        return self.radiance(normal, view_dir, albedo)
