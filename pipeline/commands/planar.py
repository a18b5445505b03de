"""`sigrend planar figures -o DIR`: the seed paper's plots (R&H 2001, planar light fields) as PNGs.

Thin wrapper over ``pipeline.core.planar``; see docs/planar.md for the conventions.  Figures:
lambert_filter.png, lobe_spectra.png, inverse_lighting.png, brdf_estimation.png, factorization.png.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline.core import planar as pl
from pipeline.errors import UserError
from pipeline.workdir import atomic_path

HELP = "planar (2D) light-field theory: reproduce the seed paper's figures"

FIGURES = ("lambert_filter.png", "lobe_spectra.png", "inverse_lighting.png", "brdf_estimation.png", "factorization.png")
LABEL_COLORS = {pl.WELL: "tab:green", pl.ILL_CONDITIONED: "tab:orange", pl.ILL_POSED: "tab:red"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="planar_command", metavar="ACTION", required=True)
    fig = sub.add_parser("figures", help="write the seed paper's plots as PNG files")
    fig.add_argument("-o", "--output", required=True, type=Path, help="folder for the PNG files")
    fig.add_argument(
        "--noise", type=float, default=1e-3, help="noise std on each light-field coefficient, relative to the largest one"
    )
    fig.add_argument("--seed", type=int, default=2001, help="random seed of the noise")
    fig.add_argument("--dpi", type=int, default=110, help="resolution of the PNG files")


def main(args: argparse.Namespace) -> int:
    if not (0.0 <= args.noise < 1.0):
        raise UserError(f"--noise {args.noise} is outside [0, 1); give a relative noise such as 1e-3")
    if not (30 <= args.dpi <= 600):
        raise UserError(f"--dpi {args.dpi} is outside 30..600; pick e.g. 110")
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out} exists and is not a folder; give a folder for -o")
    written = write_figures(out, noise=args.noise, seed=args.seed, dpi=args.dpi)
    for path in written:
        print(path)
    return 0


# ----------------------------------------------------------------------------- figure data


def sample_lighting(band: int) -> np.ndarray:
    """Two von Mises lights on a dim ambient, truncated to ``band`` (the figures' "true" lighting)."""
    theta = pl.circle_grid(256)
    radiance = 0.2 + np.exp(20.0 * (np.cos(theta - 1.0) - 1.0)) + 0.6 * np.exp(60.0 * (np.cos(theta + 2.0) - 1.0))
    return pl.fourier_coefficients(radiance, band)


def _noisy(rng, coeffs, noise_rel):
    sigma = noise_rel * np.abs(coeffs).max()
    return coeffs + sigma * (rng.normal(size=coeffs.shape) + 1j * rng.normal(size=coeffs.shape)) / np.sqrt(2), sigma


def _save(fig, path: Path, dpi: int) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", bbox_inches="tight")
    return path


def _label_scatter(ax, p, gain, labels, **kwargs):
    for label, color in LABEL_COLORS.items():
        sel = labels == label
        if np.any(sel):
            ax.scatter(p[sel], np.maximum(gain[sel], 1e-18), color=color, label=label, zorder=3, **kwargs)


def write_figures(out: Path, *, noise: float = 1e-3, seed: int = 2001, dpi: int = 110) -> list[Path]:
    """Write the five figures into ``out``; returns their paths in FIGURES order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    written = []
    makers = (_fig_lambert, _fig_lobes, _fig_inverse_lighting, _fig_brdf_estimation, _fig_factorization)
    for name, maker in zip(FIGURES, makers):
        fig = maker(plt, rng, noise)
        written.append(_save(fig, out / name, dpi))
        plt.close(fig)
    return written


def _fig_lambert(plt, rng, noise):
    band = 16
    p = pl.frequencies(band)
    closed = pl.lambert_filter(band)
    numeric = pl.transfer_coefficients(pl.Lambertian(), band, 0)[:, 0].real
    energy = np.sum(pl.lambert_filter(2000)[np.abs(pl.frequencies(2000)) <= 2] ** 2) * 16.0
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].stem(p, closed, basefmt="k-")
    axes[0].plot(p, numeric, "x", color="tab:red", label="quadrature")
    axes[0].set(xlabel="frequency p", ylabel=r"$\hat\rho_p$", title="Lambertian filter (closed form, stems)")
    axes[0].legend()
    axes[1].semilogy(p[closed != 0], np.abs(closed[closed != 0]), "o-", label=r"$|\hat\rho_p|$, even p and ±1")
    pp = np.arange(2, band + 1, 2)
    axes[1].semilogy(pp, 1.0 / (2 * np.pi * pp**2), "--", label=r"$1/(2\pi p^2)$")
    axes[1].set(
        xlabel="frequency p", ylabel="magnitude", title=f"odd p > 1 exactly 0; |p| ≤ 2 holds {100 * energy:.2f}% of the energy"
    )
    axes[1].legend()
    fig.suptitle(
        r"2D Lambertian transfer $\hat\rho=\frac{1}{2}\max(\cos\theta_i',0)$: "
        r"$\hat\rho_{2k}=(-1)^{k+1}/(2\pi(4k^2-1))$, $\hat\rho_{\pm1}=1/8$"
    )
    fig.tight_layout()
    return fig


def _fig_lobes(plt, rng, noise):
    band = 40
    p = np.arange(0, band + 1)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for s in (4, 16, 64, 256):
        exact = pl.reflected_angle_spectrum(pl.Phong(s), band)[band:]
        (line,) = axes[0].semilogy(p, np.maximum(np.abs(exact), 1e-12), label=f"s = {s}")
        axes[0].semilogy(p, np.exp(-(p**2) / (2.0 * s)), "--", color=line.get_color())
    for sigma in (0.4, 0.2, 0.1, 0.05):
        exact = pl.reflected_angle_spectrum(pl.Microfacet(sigma), band)[band:]
        (line,) = axes[1].semilogy(p, np.maximum(np.abs(exact), 1e-12), label=f"σ = {sigma}")
        axes[1].semilogy(p, np.exp(-((sigma * p) ** 2)), "--", color=line.get_color())
    axes[0].set(
        title=r"Phong $\cos^s$ lobe (dashed: $e^{-p^2/2s}$)",
        xlabel="frequency p",
        ylabel=r"normalized $|\rho_p|$ of the lobe in $\theta_i'+\theta_o'$",
        ylim=(1e-6, 2),
    )
    axes[1].set(title=r"microfacet, Beckmann σ (dashed: $e^{-(\sigma p)^2}$)", xlabel="frequency p", ylim=(1e-6, 2))
    for ax in axes:
        ax.legend()
    fig.suptitle("Specular lobes are low-pass filters whose width shrinks as the lobe sharpens")
    return fig


def _fig_inverse_lighting(plt, rng, noise):
    band, band_q = 16, 24
    p = pl.frequencies(band)
    lighting = sample_lighting(band)
    theta = np.linspace(-np.pi, np.pi, 721)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    axes[1].plot(theta, pl.fourier_synthesis(lighting, theta), "k", lw=2.5, label="true lighting")
    for name, brdf, marker in (("mirror", pl.Mirror(), "o"), ("Lambertian", pl.Lambertian(), "s")):
        rho = pl.transfer_coefficients(brdf, band, band_q)
        field, sigma = _noisy(rng, pl.reflected_field(lighting, rho), noise)
        signal = np.sqrt(np.mean(np.abs(lighting) ** 2))
        gain = pl.lighting_gain(rho)
        labels = pl.lighting_conditioning(rho, sigma, signal)
        axes[0].semilogy(p, np.maximum(gain, 1e-18), ":", color="gray")
        _label_scatter(axes[0], p, gain, labels, marker=marker, s=28)
        axes[0].annotate(
            name,
            (p[band + 4], gain[band + 4]),
            textcoords="offset points",
            xytext=(8, 8 if name == "mirror" else -14),
            fontsize=9,
        )
        recovered = pl.inverse_lighting(field, rho, noise=sigma, signal=signal)
        axes[1].plot(theta, pl.fourier_synthesis(recovered, theta), label=f"from {name} (regularized)")
    handles, names = axes[0].get_legend_handles_labels()
    unique = dict(zip(names, handles))
    axes[0].legend(unique.values(), unique.keys(), loc="center left", framealpha=0.95)
    axes[0].set(
        xlabel="frequency p",
        ylabel=r"gain $2\pi(\sum_q|\hat\rho_{-p,q}|^2)^{1/2}$",
        title=f"inverse-lighting conditioning, noise {noise:g} of max |B|",
        ylim=(1e-19, 10),
    )
    axes[1].set(xlabel="θ (rad)", ylabel="L(θ)", title="lighting recovered from noisy light fields")
    axes[1].legend(fontsize=8)
    return fig


def _fig_brdf_estimation(plt, rng, noise):
    band, band_q = 24, 32
    p = pl.frequencies(band)
    phong = pl.Phong(32)
    rho = pl.transfer_coefficients(phong, band, band_q)
    theta_i = np.linspace(-np.pi / 2, np.pi / 2, 361)
    theta_o = 0.4
    truth = pl.light_field_synthesis(rho, theta_i, [theta_o])[:, 0]
    sources = {
        "directional source": np.full(2 * band + 1, 1.0 / (2 * np.pi), complex),
        "area source (width 0.5 rad)": np.exp(-(p**2) * 0.25 / 2.0) / (2 * np.pi) + 0j,
    }
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    axes[1].plot(theta_i, truth, "k", lw=2.5, label=f"true Phong s=32 (band {band})")
    for (name, lighting), marker in zip(sources.items(), ("o", "s")):
        field, sigma = _noisy(rng, pl.reflected_field(lighting, rho), noise)
        signal = np.sqrt(np.mean(np.abs(rho) ** 2))
        gain = 2 * np.pi * np.abs(lighting)
        labels = pl.brdf_conditioning(lighting, sigma, signal)
        axes[0].semilogy(p, np.maximum(gain, 1e-18), ":", color="gray")
        _label_scatter(axes[0], p, gain, labels, marker=marker, s=28)
        axes[0].annotate(name, (p[band + 6], gain[band + 6]), textcoords="offset points", xytext=(10, 6), fontsize=9)
        estimate = pl.estimate_brdf(field, lighting, noise=sigma, signal=signal)
        axes[1].plot(theta_i, pl.light_field_synthesis(estimate, theta_i, [theta_o])[:, 0], label=f"under {name}")
    handles, names = axes[0].get_legend_handles_labels()
    unique = dict(zip(names, handles))
    axes[0].legend(unique.values(), unique.keys(), loc="lower center", framealpha=0.95)
    axes[0].set(
        xlabel="frequency p",
        ylabel=r"gain $2\pi|L_p|$",
        title=f"BRDF-estimation conditioning, noise {noise:g} of max |B|",
        ylim=(1e-26, 10),
    )
    axes[1].set(
        xlabel=r"$\theta_i'$ (rad)",
        ylabel=rf"$\hat\rho(\theta_i', \theta_o'={theta_o})$",
        title="transfer slice recovered (Wiener-regularized)",
    )
    axes[1].legend(fontsize=8)
    return fig


def _fig_factorization(plt, rng, noise):
    band, band_q = 12, 16
    lighting = sample_lighting(band)
    brdf = pl.Phong(24)
    kernel = pl.transfer_coefficients(brdf, band, band_q, cosine_outgoing=True)
    field, sigma = _noisy(rng, pl.reflected_field(lighting, kernel), noise)
    result = pl.factorize_field(field)
    scale = lighting[band].real  # factorize_field fixes L_0 = 1: undo for display
    rec_l, rec_k = result.lighting * scale, result.kernel / scale
    alpha = np.linspace(0, 2 * np.pi, 181)
    theta_o = np.linspace(-np.pi / 2, np.pi / 2, 91)
    true_img = pl.light_field_synthesis(field, alpha, theta_o)
    rec_img = pl.light_field_synthesis(pl.reflected_field(rec_l, rec_k), alpha, theta_o)
    theta = np.linspace(-np.pi, np.pi, 721)
    theta_i = np.linspace(-np.pi / 2, np.pi / 2, 181)

    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    extent = (theta_o[0], theta_o[-1], alpha[-1], alpha[0])
    vmax = true_img.max()
    for ax, img, title in (
        (axes[0, 0], true_img, "observed (noisy) light field"),
        (axes[0, 1], rec_img, "rebuilt from recovered L and K"),
    ):
        im = ax.imshow(img, extent=extent, aspect="auto", vmin=0, vmax=vmax, cmap="magma")
        ax.set(xlabel=r"$\theta_o'$ (rad)", ylabel="α (rad)", title=title + r": $\tilde B(\alpha,\theta_o')=B\cos\theta_o'$")
        fig.colorbar(im, ax=ax)
    axes[1, 0].plot(theta, pl.fourier_synthesis(lighting, theta), "k", lw=2.5, label="true")
    axes[1, 0].plot(theta, pl.fourier_synthesis(rec_l, theta), "--", color="tab:orange", label="recovered")
    axes[1, 0].set(xlabel="θ (rad)", ylabel="L(θ)", title=f"lighting (band {band}), scale fixed by the mean")
    for theta_fixed, color in ((0.0, "tab:blue"), (0.6, "tab:green")):
        axes[1, 1].plot(
            theta_i,
            pl.light_field_synthesis(kernel, theta_i, [theta_fixed])[:, 0],
            color=color,
            lw=2.5,
            label=rf"true, $\theta_o'={theta_fixed}$",
        )
        axes[1, 1].plot(theta_i, pl.light_field_synthesis(rec_k, theta_i, [theta_fixed])[:, 0], "--", color="tab:orange")
    axes[1, 1].set(
        xlabel=r"$\theta_i'$ (rad)", ylabel=r"$K=\rho\cos\theta_i'\cos\theta_o'$", title="BRDF kernel slices (dashed: recovered)"
    )
    for ax in axes[1]:
        ax.legend(fontsize=8)
    err_l = np.linalg.norm(rec_l - lighting) / np.linalg.norm(lighting)
    err_k = np.linalg.norm(rec_k - kernel) / np.linalg.norm(kernel)
    fig.suptitle(
        f"Factorization of a Phong (s=24) light field, noise {noise:g}: relative error "
        f"L {err_l:.2g}, K {err_k:.2g} (up to one global scale)"
    )
    fig.tight_layout()
    return fig
