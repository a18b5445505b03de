"""Regularized deconvolution in SH space: chunked normal equations, per-band conditioning labels,
variable-projection BRDF fits, leave-views-out model selection (pure NumPy/SciPy).

Inverse lighting (DESIGN.md "The inverse problems"): for a fixed BRDF the radiance is linear in the
lighting, B_c = A_c L_c (pipeline.core.forward), so L_c solves the weighted normal equations
(A_c^T W A_c) L_c = A_c^T W b_c.  They are accumulated chunk by chunk (memory O(K^2), time linear
in N) and separately per validation fold, so that held-out errors of every order <= L come from
one pass over the data (the SH design of order L' < L is the first (L'+1)^2 columns).

Per-band conditioning.  For band l, let g_l = sqrt(lambda_min(G_ll) / W) be the RMS radiance change
per unit coefficient in the least observable direction of the band (G_ll: the band's block of the
channel-averaged normal matrix, W: the total weight), and sigma the per-sample noise (residual RMS,
floored at ``noise_floor`` x RMS radiance because calibration and model errors never vanish).
The band's signal-to-noise ratio is snr_l = g_l |L_0| / sigma with |L_0| the RMS of the DC
lighting coefficient: the radiance that a band coefficient as large as the DC term would produce,
over the noise.  Labels:
  ill-posed        g_max,l <= 1e-6 g_max,0: the transfer is (numerically) zero in the band
                   (odd l > 1 of a Lambertian: Â_l = 0 exactly) or nothing covers it -> zeroed;
  ill-conditioned  snr_l < min_snr (default 10, i.e. a coefficient of 10% of the DC term is at the
                   noise level) -> Tikhonov ridge (W / V) sigma^2 / tau^2 with prior scale
                   tau = band_prior |L_0|, treating the noise as correlated within each of the V
                   views (calibration, model error) and independent between views, so the ridge
                   does not vanish as the number of pixels grows;
  recoverable      otherwise -> (numerically) unregularized.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.brdf import WIDTH_PARAM, Brdf
from pipeline.core.sh import band_of_index, num_coeffs
from pipeline.core.threads import thread_map

LABELS = ("recoverable", "ill-conditioned", "ill-posed")


@dataclass
class NormalEquations:
    """Weighted normal equations per fold and channel, accumulated chunk by chunk.

    gram (F, C, K, K), rhs (F, C, K), btb (F, C), weight (F,), count (F,).  ``shared`` = True when
    every channel uses the same design (Lambertian: A_c = rho_c D, scale applied at solve time),
    then gram has C = 1.
    """

    order: int
    folds: int
    shared: bool
    gram: np.ndarray = field(init=False)
    rhs: np.ndarray = field(init=False)
    btb: np.ndarray = field(init=False)
    weight: np.ndarray = field(init=False)
    count: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        k = num_coeffs(self.order)
        self.gram = np.zeros((self.folds, 1 if self.shared else 3, k, k))
        self.rhs = np.zeros((self.folds, 3, k))
        self.btb = np.zeros((self.folds, 3))
        self.weight = np.zeros(self.folds)
        self.count = np.zeros(self.folds, dtype=np.int64)

    def add(self, designs: np.ndarray, radiance: np.ndarray, weight: np.ndarray, fold: np.ndarray, *, gram: bool = True) -> None:
        """Add one chunk: designs (Cd, N, K) with Cd = 1 (shared) or 3, radiance (N, 3),
        weight (N,), fold (N,) ints in [0, folds).  ``gram`` False: all but the gram (the
        designs' gram is in already: retargeted).

        Samples files list each image's samples together, so folds (= views) come in runs: each
        run is a view of the chunk (no copy); shuffled folds are permuted once instead.
        """
        weight = np.asarray(weight, dtype=float)
        fold = np.asarray(fold)
        unit = bool(np.all(weight == 1.0))
        starts = np.concatenate([[0], np.flatnonzero(np.diff(fold)) + 1])
        if len(starts) > 8 * self.folds:  # shuffled: permute once
            order = np.argsort(fold, kind="stable")
            designs, radiance, weight, fold = designs[:, order], radiance[order], weight[order], fold[order]
            starts = np.concatenate([[0], np.flatnonzero(np.diff(fold)) + 1])
        stops = np.append(starts[1:], len(fold))
        sw = None if unit else np.sqrt(weight)
        runs: dict[int, list[tuple[int, int, np.ndarray]]] = {}  # fold -> its runs (lo, hi, weighted radiance)
        for lo, hi in zip(starts, stops):
            f = int(fold[lo])
            b = radiance[lo:hi] if unit else radiance[lo:hi] * sw[lo:hi, None]
            runs.setdefault(f, []).append((int(lo), int(hi), b))
            self.btb[f] += (b * b).sum(axis=0)
            self.weight[f] += weight[lo:hi].sum()
            self.count[f] += hi - lo

        def accumulate(f: int, c: int) -> None:  # one (fold, channel) block: no two tasks share one
            for lo, hi, b in runs[f]:
                if not gram:  # A'W b as A' (sqrt(W) b): no weighted copy of the design
                    bw = b if unit else b * sw[lo:hi, None]
                    self.rhs[f, c] += designs[c, lo:hi].T @ bw[:, c]
                    continue
                a = designs[c, lo:hi] if unit else designs[c, lo:hi] * sw[lo:hi, None]
                self.gram[f, c] += a.T @ a
                if self.shared:
                    self.rhs[f] += (a.T @ b).T
                else:
                    self.rhs[f, c] += a.T @ b[:, c]

        if not gram and self.shared:
            raise ValueError("NormalEquations.add(gram=False): per-channel designs only")
        # the (fold, channel) blocks by one thread per core: BLAS products release the GIL
        thread_map(lambda fc: accumulate(*fc), [(f, c) for f in runs for c in range(designs.shape[0])])

    def retargeted(self, designs: np.ndarray, radiance: np.ndarray, weight: np.ndarray, fold: np.ndarray) -> "NormalEquations":
        """The equations of the same ``designs``, weights and folds as the one chunk added to
        these, for another ``radiance``: the gram shared (the expensive part, N K^2 per channel),
        right-hand sides and btb accumulated anew (N K)."""
        out = NormalEquations(self.order, self.folds, self.shared)
        out.gram = self.gram
        out.add(designs, radiance, weight, fold, gram=False)
        return out

    def channel_system(self, folds: np.ndarray | slice, scale: np.ndarray | None = None, order: int | None = None):
        """Summed (over ``folds``) per-channel (G (3,K',K'), h (3,K'), btb (3,), W) truncated to
        ``order``; ``scale`` (3,) multiplies a shared design per channel (rho_c)."""
        k = num_coeffs(self.order if order is None else order)
        g = self.gram[folds, :, :k, :k].sum(axis=0)  # truncated before the sum: an order's blocks only
        h = self.rhs[folds, :, :k].sum(axis=0)
        if self.shared:
            s = np.ones(3) if scale is None else np.asarray(scale, dtype=float)
            g = (s**2)[:, None, None] * g[0][None]
            h = s[:, None] * h
        return g, h, self.btb[folds].sum(axis=0), float(self.weight[folds].sum())


def residual_sum(g: np.ndarray, h: np.ndarray, btb: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Weighted RSS per channel from the normal equations: b'Wb - 2 x'h + x'Gx (3,)."""
    return btb - 2.0 * np.einsum("ck,kc->c", h, x) + np.einsum("kc,ckj,jc->c", x, g, x)


@dataclass
class LightingFit:
    coeffs: np.ndarray  # ((L+1)^2, 3)
    labels: list[str]  # per band
    bands: list[dict]  # per band diagnostics
    noise_sigma: float  # per-sample noise used for labels (radiance units)
    residual_rms: float  # weighted training RMS residual
    ridge: np.ndarray  # (K,) diagonal regularization added


def band_gains(g_mean: np.ndarray, weight: float, order: int) -> tuple[np.ndarray, np.ndarray]:
    """(g_min, g_max) per band: sqrt of the extreme eigenvalues of the band's block of G / W."""
    gmin, gmax = np.zeros(order + 1), np.zeros(order + 1)
    for l in range(order + 1):
        sl = slice(l * l, (l + 1) ** 2)
        ev = np.linalg.eigvalsh(g_mean[sl, sl] / max(weight, 1e-300))
        gmin[l], gmax[l] = np.sqrt(max(ev[0], 0.0)), np.sqrt(max(ev[-1], 0.0))
    return gmin, gmax


def _solve_ridge(g: np.ndarray, h: np.ndarray, ridge: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Per channel (G + diag(ridge)) x = h on the ``keep`` coefficients; others are 0. -> (K, 3)."""
    k = g.shape[1]
    x = np.zeros((k, 3))
    idx = np.nonzero(keep)[0]
    if idx.size == 0:
        return x
    a = (g if idx.size == k else g[:, idx[:, None], idx[None, :]]) + np.diag(ridge[idx])
    try:  # the three channels in one batched LAPACK call
        x[idx] = np.linalg.solve(a, h[:, idx, None])[..., 0].T
    except np.linalg.LinAlgError:
        for c in range(3):
            x[idx, c] = np.linalg.lstsq(a[c], h[c, idx], rcond=None)[0]
    return x


def solve_lighting(
    g: np.ndarray,
    h: np.ndarray,
    btb: np.ndarray,
    weight: float,
    count: int,
    order: int,
    *,
    noise_floor: float = 0.005,
    min_snr: float = 10.0,
    band_prior: float = 0.3,
    labels: list[str] | None = None,
    noise_sigma: float | None = None,
    independent_groups: int = 1,
    posed_ratio: float = 1e-6,
) -> LightingFit:
    """Regularized lighting from per-channel normal equations (see the module docstring).

    ``labels`` / ``noise_sigma`` given: reuse them (held-out refits use the full-data labels).
    ``posed_ratio``: a band whose largest gain is at most this fraction of band 0's is ill-posed
    (1e-6: exact zeros of closed-form transfer; a quadrature transfer's accuracy is coarser).
    Returns coefficients ((L+1)^2, 3) in the real orthonormal basis of DESIGN.md.
    """
    k = num_coeffs(order)
    g, h = g[:, :k, :k], h[:, :k]
    bands = band_of_index(order)
    g_mean = g.mean(axis=0)
    gmin, gmax = band_gains(g_mean, weight, order)
    eps = 1e-10 * max(np.trace(g_mean) / k, 1e-300)
    posed = gmax > posed_ratio * max(gmax[0], 1e-300)
    keep = posed[bands]
    x0 = _solve_ridge(g, h, np.full(k, eps), keep)
    rss = residual_sum(g, h, btb, x0)
    dof = max(count - keep.sum(), 1)
    rms_signal = float(np.sqrt(max(btb.mean(), 0.0) / max(weight, 1e-300)))
    measured = float(np.sqrt(max(rss.mean(), 0.0) / max(weight, 1e-300) * count / dof))
    if noise_sigma is None:
        noise_sigma = max(measured, noise_floor * rms_signal, 1e-300)
    dc = float(np.sqrt(np.mean(x0[0] ** 2))) or 1.0
    snr = gmin * dc / noise_sigma
    if labels is None:
        labels = [
            ("ill-posed" if not posed[l] else "ill-conditioned" if snr[l] < min_snr else "recoverable") for l in range(order + 1)
        ]
    labels = list(labels[: order + 1])
    tau = band_prior * dc
    # G sums N samples, but calibration and model errors are correlated within a view: the noise
    # is taken as independent only between ``independent_groups`` groups (views), so the ridge is
    # (W / groups) sigma^2 / tau^2 and the shrinkage of a band, G/(G + ridge) ~
    # groups snr'^2 / (groups snr'^2 + 1) with snr' = g_l tau / sigma, does not vanish as N grows.
    band_ridge = np.array(
        [weight / max(independent_groups, 1) * noise_sigma**2 / tau**2 if lab == "ill-conditioned" else eps for lab in labels]
    )
    keep = np.array([lab != "ill-posed" for lab in labels])[bands]
    ridge = band_ridge[bands]
    x = _solve_ridge(g, h, ridge, keep)
    rss = residual_sum(g, h, btb, x)
    info = [
        {
            "l": l,
            "label": labels[l],
            "gain_min": float(gmin[l]),
            "gain_max": float(gmax[l]),
            "snr": float(snr[l]),
            "ridge": float(band_ridge[l]) if labels[l] == "ill-conditioned" else 0.0,
            "energy": float((x[l * l : (l + 1) ** 2] ** 2).sum()),
        }
        for l in range(order + 1)
    ]
    return LightingFit(
        x, labels, info, float(noise_sigma), float(np.sqrt(max(rss.sum(), 0.0) / (3 * max(weight, 1e-300)))), ridge
    )


def data_labels(bands: list[dict], noise_sigma: float, data_sigma: float, min_snr: float = 10.0) -> list[dict]:
    """The bands of a LightingFit (``bands``, labelled against ``noise_sigma``, the fit's residual:
    model error included) labelled again against ``data_sigma``, the photos' own noise measured
    apart from model error (pipeline.core.noise): what the data determine through this transfer if
    the forward model were exact.  snr_data = snr * noise_sigma / data_sigma; ill-posed stays
    ill-posed.  Each band keeps whether its ridge shrank it as ``regularized`` (the fit's own label
    was ill-conditioned); with no usable ``data_sigma`` the labels are kept and snr_data is None."""
    usable = np.isfinite(data_sigma) and data_sigma > 0
    out = []
    for b in bands:
        snr_data = b["snr"] * noise_sigma / data_sigma if usable else None
        label = (
            b["label"] if not usable or b["label"] == "ill-posed" else "recoverable" if snr_data >= min_snr else "ill-conditioned"
        )
        out.append({**b, "label": label, "snr_data": snr_data, "regularized": b["label"] == "ill-conditioned"})
    return out


def cross_validate_orders(eqs: NormalEquations, orders: list[int], scale: np.ndarray | None = None, **solve_kwargs) -> list[dict]:
    """Leave-one-fold-out errors of every candidate order from one set of per-fold normal equations.

    Per order: the full-data fit fixes the band labels and the noise; each fold is refit without
    its own rows and scored on them.  Returns one dict per order: order, params, train_rmse,
    validation_rmse (and validation_rmse_per_channel (3,)), seconds.
    """
    out = []
    all_folds = slice(None)
    if "noise_sigma" not in solve_kwargs:
        # one noise level for every candidate: the residual of the richest model
        top = max(orders)
        g, h, btb, w = eqs.channel_system(all_folds, scale, top)
        solve_kwargs = {
            **solve_kwargs,
            "noise_sigma": solve_lighting(g, h, btb, w, int(eqs.count.sum()), top, **solve_kwargs).noise_sigma,
        }
    for order in orders:
        t0 = time.perf_counter()
        g, h, btb, w = eqs.channel_system(all_folds, scale, order)
        full = solve_lighting(g, h, btb, w, int(eqs.count.sum()), order, **solve_kwargs)
        val_rss, val_w = np.zeros(3), 0.0
        for f in range(eqs.folds):
            if eqs.count[f] == 0:
                continue
            train = np.array([i for i in range(eqs.folds) if i != f])
            if eqs.count[train].sum() == 0:
                continue
            gt, ht, bt, wt = eqs.channel_system(train, scale, order)
            fit = solve_lighting(gt, ht, bt, wt, int(eqs.count[train].sum()), order, **{**solve_kwargs, "labels": full.labels})
            gv, hv, bv, wv = eqs.channel_system(np.array([f]), scale, order)
            val_rss += residual_sum(gv, hv, bv, fit.coeffs)
            val_w += wv
        per_channel = np.sqrt(np.maximum(val_rss, 0.0) / val_w) if val_w else np.full(3, np.nan)
        out.append(
            {
                "order": order,
                "params": 3 * num_coeffs(order),
                "train_rmse": full.residual_rms,
                "validation_rmse": float(np.sqrt(max(val_rss.sum(), 0.0) / (3 * val_w))) if val_w else float("nan"),
                "validation_rmse_per_channel": [float(x) for x in per_channel],
                "seconds": time.perf_counter() - t0,
                "fit": full,
            }
        )
    return out


# ---------------------------------------------------------------------------------------------
# BRDF from known lighting: variable projection over the lobe width
# ---------------------------------------------------------------------------------------------


@dataclass
class BrdfData:
    """Per-sample quantities for BRDF fits under fixed lighting (pipeline.core.forward):
    diffuse (N, 3) = sum Â_l/pi L_lm,c Y_lm(n) (radiance per unit albedo), bands (N, L+1, 3) =
    per-band lighting at the mirror direction, grazing (N,) Schlick weight, radiance (N, 3),
    weight (N,), fold (N,), cos_view (N,) = n.v (for view-dependent lobe filters)."""

    diffuse: np.ndarray
    bands: np.ndarray
    grazing: np.ndarray
    radiance: np.ndarray
    weight: np.ndarray
    fold: np.ndarray
    cos_view: np.ndarray

    def subset(self, rows: np.ndarray) -> "BrdfData":
        return BrdfData(
            *(getattr(self, f)[rows] for f in ("diffuse", "bands", "grazing", "radiance", "weight", "fold", "cos_view"))
        )


def _nnls_2(g: np.ndarray, h: np.ndarray) -> np.ndarray:
    """min x'Gx - 2h'x over x >= 0 for a 1x1 or 2x2 G (exact: try the interior, then the faces)."""
    n = g.shape[0]
    best, best_val = np.zeros(n), 0.0
    candidates = []
    try:
        candidates.append(np.linalg.solve(g + 1e-300 * np.eye(n), h))
    except np.linalg.LinAlgError:
        pass
    for i in range(n):
        x = np.zeros(n)
        if g[i, i] > 0:
            x[i] = h[i] / g[i, i]
        candidates.append(x)
    for x in candidates:
        if np.all(x >= 0):
            val = x @ g @ x - 2.0 * h @ x
            if val < best_val:
                best, best_val = x, val
    return best


def linear_brdf(data: BrdfData, model: str, filt: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, float]:
    """Non-negative least squares for (albedo_c, lobe colour_c) at fixed per-sample lobe filters
    ``filt`` (N, L+1) (A_l of each sample's view); the lobe colour is Phong's specular_weight or
    the microfacet's f0 (pipeline.core.brdf.LOBE_COLOR_PARAM).

    Returns albedo (3,), lobe colour (3,) and the weighted RSS (all channels)."""
    w = data.weight
    albedo, spec, rss = np.zeros(3), np.zeros(3), 0.0
    lobe = None if model == "lambert" else np.einsum("nlc,nl->nc", data.bands, filt)  # (N, 3)
    for c in range(3):
        cols = [data.diffuse[:, c]]
        target = data.radiance[:, c]
        if model == "phong":
            cols.append(lobe[:, c])
        elif model == "microfacet":
            cols.append(lobe[:, c] * (1.0 - data.grazing))
            target = target - lobe[:, c] * data.grazing
        a = np.stack(cols, axis=1)
        g = a.T @ (a * w[:, None])
        h = a.T @ (target * w)
        x = _nnls_2(g, h)
        albedo[c] = x[0]
        if len(x) > 1:
            spec[c] = x[1]
        rss += float(target**2 @ w - 2.0 * h @ x + x @ g @ x)
    return albedo, spec, max(rss, 0.0)


WIDTH_BOUNDS = {"phong": (1.0, 5000.0), "microfacet": (0.02, 1.0)}


def angular_width(model: str, width: float) -> float:
    """Lobe width as an angle-like number (radians ~): sigma for microfacet, 1/sqrt(s) for Phong."""
    return float(width) if model == "microfacet" else 1.0 / np.sqrt(float(width))


@dataclass(frozen=True)
class BrdfFit:
    """fit_brdf's result: the BRDF and its weighted mean square residual (all channels); for a lobe
    model its width, the residual profile over the log grid of widths ([{width param: w, "mse": m}]),
    whether the width is recoverable and the widths within noise of the best [lo, hi]."""

    brdf: Brdf
    mse: float
    width: float | None = None
    profile: list = field(default_factory=list)
    width_recoverable: bool | None = None
    width_interval: list | None = None

    def width_report(self) -> dict:
        """report.json's brdf_width: everything but the BRDF."""
        out = {"mse": self.mse, "width": self.width, "profile": self.profile, "width_recoverable": self.width_recoverable}
        if self.width_interval is not None:
            out["width_interval"] = self.width_interval
        return out


def fit_brdf(
    data: BrdfData, model: str, filter_fn, *, noise_floor: float = 0.005, grid: int = 13, max_evals: int = 25
) -> BrdfFit:
    """Variable projection: Brent's bounded search (in log width, between the best grid point's
    neighbours) over the lobe width; for each
    width :func:`linear_brdf` gives the linear parameters.  ``filter_fn(model, width)`` -> A_l.

    The residual profile on a log grid of widths is kept: the width counts as recoverable when the
    widths whose mean square residual is within sigma^2 of the best (sigma: residual RMS, floored
    at ``noise_floor`` x RMS radiance) span at most a factor 3 in angular width; otherwise the
    profile is flat within noise and the width is reported unrecoverable.
    """
    from scipy.optimize import minimize_scalar

    wsum = float(data.weight.sum())
    rms_signal = float(np.sqrt((data.radiance**2 * data.weight[:, None]).sum() / (3 * wsum)))
    if model == "lambert":
        albedo, spec, rss = linear_brdf(data, model, None)
        return BrdfFit(Brdf("lambert", albedo=albedo), rss / (3 * wsum))
    lo, hi = WIDTH_BOUNDS[model]
    param = WIDTH_PARAM[model]

    def mse_at(log_w: float) -> float:
        return linear_brdf(data, model, filter_fn(model, float(np.exp(log_w)), data.cos_view))[2] / (3 * wsum)

    log_grid = np.linspace(np.log(lo), np.log(hi), grid)
    profile = np.array([mse_at(x) for x in log_grid])
    start = float(log_grid[int(np.argmin(profile))])
    step = float(log_grid[1] - log_grid[0])
    # Brent's bounded search between the best grid point's neighbours (the bracket of its minimum)
    found = minimize_scalar(
        mse_at,
        bounds=(max(start - step, np.log(lo)), min(start + step, np.log(hi))),
        method="bounded",
        options={"xatol": 1e-3, "maxiter": max_evals},
    )
    best_log = float(found.x) if np.isfinite(found.fun) else start
    if mse_at(best_log) > profile.min():
        best_log = start
    width = float(np.exp(best_log))
    albedo, spec, rss = linear_brdf(data, model, filter_fn(model, width, data.cos_view))
    mse = rss / (3 * wsum)
    sigma2 = max(mse, (noise_floor * rms_signal) ** 2)
    accepted = np.exp(log_grid[profile - min(mse, profile.min()) <= sigma2])
    ang = sorted(angular_width(model, x) for x in accepted) if accepted.size else [angular_width(model, width)]
    spread = ang[-1] / max(ang[0], 1e-300)
    recoverable = bool(spread <= 3.0 and np.max(spec) > 0)
    return BrdfFit(
        Brdf.from_lobe(model, albedo, spec, width),
        mse,
        width,
        [{param: float(np.exp(x)), "mse": float(m)} for x, m in zip(log_grid, profile)],
        recoverable,
        [float(accepted.min()), float(accepted.max())] if accepted.size else [width, width],
    )


def brdf_mse(data: BrdfData, brdf: Brdf, filter_fn) -> float:
    """Weighted mean square residual of a fixed BRDF on ``data`` (all channels)."""
    model = brdf.model
    pred = np.asarray(brdf.albedo)[None, :] * data.diffuse
    if model != "lambert":
        filt = filter_fn(model, brdf.lobe_width, data.cos_view)
        lobe = np.einsum("nlc,nl->nc", data.bands, filt)
        spec = brdf.lobe_color[None, :]
        k = spec if model == "phong" else spec * (1.0 - data.grazing[:, None]) + data.grazing[:, None]
        pred = pred + k * lobe
    r = data.radiance - pred
    return float((r**2 * data.weight[:, None]).sum() / (3 * data.weight.sum()))
