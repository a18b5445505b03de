"""Benchmark suites of the whole pipeline for `sigrend bench`: ``pipeline`` and ``stability``.

``stability`` (seconds): the seed's well-posedness table in 3D, measured.  Light-field samples of
a sphere seen from many directions are generated with the frequency-space forward model
(pipeline.core.forward), Gaussian noise is added, and the inverse problems are solved by plain
(unregularized) least squares, so the conditioning of each problem shows undamped:
  * inverse lighting: relative error of each SH band l of the recovered lighting vs noise, for a
    Lambertian and a glossy sphere (R&H: from a Lambertian object only l <= 2 is recoverable,
    odd l > 1 not at all; a sharp lobe carries high bands);
  * BRDF estimation (the fit's variable projection, pipeline.core.solve.fit_brdf): relative error
    of the recovered lobe width and specular weight vs noise, under sharp lighting (small area lights) and
    soft lighting (a smooth order-2 sky) (R&H: the
    lobe width is recoverable only when the lighting has the frequencies the lobe passes).
Writes stability_lighting.png, stability_brdf.png and stability.csv.

``pipeline`` (about 20 minutes; --quick: 5): small synthetic captures rendered by the
angular-domain renderer (pipeline.core.render: a Lambertian and a principled sphere), run through
samples -> fit (the physical forward model) -> relight with a sweep of SH order, data amount
(samples fitted, sample stride, number of views) and fit mode; each configuration's time and accuracy
(lighting error per band against the ground truth, relight error on held-out views) go to
bench.csv and bench.png (relight error against time, Pareto front marked).
"""

from __future__ import annotations

import csv
import json
import os
import shutil
from pathlib import Path

import numpy as np

from pipeline.commands.bench import BenchRow
from pipeline.core import forward
from pipeline.core.brdf import Brdf
from pipeline.core.factorization import brdf_data
from pipeline.core.procedural_envmaps import make_envmap
from pipeline.core.sh import band_of_index, band_relative_errors, num_coeffs, order_of, project_envmap
from pipeline.core.solve import fit_brdf
from pipeline.io.lighting import read_lighting_sh
from pipeline.runner import run_stage, stage_settings
from pipeline.synth import make_test_capture
from pipeline.workdir import atomic_path

NOISE_LEVELS = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1)


def _plt():
    import matplotlib  # when charts are drawn: the Agg backend chosen before pyplot loads

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def sphere_light_field(n_normals: int, n_views: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(normal, view_dir) pairs of a sphere photographed from ``n_views`` directions spread over the
    sphere: every normal facing a camera (n.v > 0.2) gives one sample per camera.  (N, 3) each."""

    def fibonacci(n):
        i = np.arange(n) + 0.5
        z = 1 - 2 * i / n
        phi = np.pi * (1 + 5**0.5) * i
        s = np.sqrt(1 - z * z)
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)

    normals = fibonacci(n_normals)
    views = fibonacci(n_views) @ _random_rotation(rng).T
    cos = normals @ views.T
    ni, vi = np.nonzero(cos > 0.2)
    return normals[ni], views[vi]


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_lighting(order: int, rng: np.random.Generator) -> np.ndarray:
    """Band-limited lighting ((order+1)^2, 3) with a natural 1/(1+l)^2 energy spectrum per band,
    DC large enough to keep the radiance positive."""
    l = band_of_index(order)
    coeffs = rng.normal(size=(num_coeffs(order), 3)) / (1.0 + l[:, None]) ** 1.0 / np.sqrt(2 * l[:, None] + 1)
    coeffs[0] = 3.0
    return coeffs


def _solve_lighting(normal, view, radiance, brdf, order) -> np.ndarray:
    """Plain least squares for the SH lighting, per channel (minimum-norm where rank deficient)."""
    terms = forward.design_terms(normal, view, order, brdf.has_lobe)
    designs = forward.channel_designs(terms, brdf, order)
    return np.stack([np.linalg.lstsq(designs[c], radiance[:, c], rcond=1e-12)[0] for c in range(3)], axis=1)


def stability_lighting(rng: np.random.Generator, order: int = 8, trials: int = 3) -> list[dict]:
    """Inverse lighting error per band vs noise, Lambertian vs glossy (rows for the CSV)."""
    normal, view = sphere_light_field(1500, 24, rng)
    scenes = {
        "lambertian": Brdf("lambert", albedo=(0.8, 0.8, 0.8)),
        "glossy (phong s=200)": Brdf("phong", albedo=(0.3, 0.3, 0.3), specular_weight=(0.6, 0.6, 0.6), exponent=200.0),
    }
    rows = []
    for scene, brdf in scenes.items():
        for noise in NOISE_LEVELS:
            errs = []
            for _ in range(trials):
                truth = test_lighting(order, rng)
                clean = forward.render_samples(truth, brdf, normal, view)
                noisy = clean + noise * clean.mean() * rng.normal(size=clean.shape)
                errs.append(band_relative_errors(_solve_lighting(normal, view, noisy, brdf, order), truth))
            med = np.median(errs, axis=0)
            for l, e in enumerate(med):
                rows.append(
                    {
                        "problem": "inverse lighting",
                        "scene": scene,
                        "noise": noise,
                        "quantity": f"band {l}",
                        "relative_error": float(e),
                    }
                )
    return rows


def samples_brdf_data(normal, view, radiance, coeffs):
    """pipeline.core.solve.BrdfData of samples under known SH lighting ``coeffs`` (one fold), built
    by the fit's own helper."""
    n = len(normal)
    return brdf_data(
        {"normal": normal, "view_dir": view, "radiance": radiance, "weight": np.ones(n), "image_id": np.zeros(n, int)}, coeffs, 1
    )


def stability_brdf(rng: np.random.Generator, trials: int = 3) -> list[dict]:
    """BRDF estimation error (lobe width, specular weight) vs noise under sharp and soft lighting."""
    normal, view = sphere_light_field(600, 16, rng)
    order = 24
    lightings = {
        "sharp (area lights)": project_envmap(make_envmap("area", 64), order),
        "soft (smooth sky)": project_envmap(make_envmap("smooth", 64), 2),
    }
    exponent, specular_weight = 200.0, 0.5
    truth = Brdf("phong", albedo=(0.4, 0.4, 0.4), specular_weight=specular_weight, exponent=exponent)
    rows = []
    for name, coeffs in lightings.items():
        clean = forward.render_samples(coeffs, truth, normal, view)
        data = samples_brdf_data(normal, view, clean, coeffs)
        l_max = data.bands.shape[1] - 1

        def filter_fn(model, width, cos_view=None, l_max=l_max, data=data):
            """Per-sample A_l (N, L+1) of the forward model, as the fit's solver asks for them."""
            return forward.sample_lobe_filters(model, width, l_max, data.cos_view if cos_view is None else cos_view)

        for noise in NOISE_LEVELS:
            w_err, s_err = [], []
            for _ in range(trials):
                data.radiance = clean + noise * clean.mean() * rng.normal(size=clean.shape)
                fit = fit_brdf(data, "phong", filter_fn, noise_floor=1e-6).brdf
                w_err.append(abs(fit.exponent / exponent - 1.0))
                s_err.append(float(np.abs(np.asarray(fit.specular_weight) - specular_weight).mean() / specular_weight))
            rows.append(
                {
                    "problem": "BRDF estimation",
                    "scene": name,
                    "noise": noise,
                    "quantity": "lobe width (Phong exponent)",
                    "relative_error": float(np.median(w_err)),
                }
            )
            rows.append(
                {
                    "problem": "BRDF estimation",
                    "scene": name,
                    "noise": noise,
                    "quantity": "specular weight",
                    "relative_error": float(np.median(s_err)),
                }
            )
    return rows


def _noise_axis(noise: np.ndarray) -> np.ndarray:
    """Noise levels for a log axis: the noiseless run is drawn at a tenth of the smallest level."""
    positive = noise[noise > 0]
    return np.where(noise > 0, noise, positive.min() / 10 if positive.size else 1e-4)


def plot_stability(rows: list[dict], out_dir: Path) -> list[Path]:
    plt = _plt()
    written = []
    light = [r for r in rows if r["problem"] == "inverse lighting"]
    scenes = list(dict.fromkeys(r["scene"] for r in light))
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.5 * len(scenes), 4.2), sharey=True)
    for ax, scene in zip(np.atleast_1d(axes), scenes):
        sub = [r for r in light if r["scene"] == scene]
        for q in dict.fromkeys(r["quantity"] for r in sub):
            pts = [r for r in sub if r["quantity"] == q]
            noise = _noise_axis(np.array([r["noise"] for r in pts]))
            ax.loglog(
                noise,
                np.maximum([r["relative_error"] for r in pts], 1e-6),
                marker="o",
                ms=3,
                label=q,
                color=plt.cm.viridis(int(q.split()[-1]) / 9),
            )
        ax.axhline(1.0, color="k", lw=0.6, ls="--")
        ax.set_title(f"inverse lighting, {scene}")
        ax.set_xlabel("noise (fraction of mean radiance; leftmost = noiseless)")
    np.atleast_1d(axes)[0].set_ylabel("relative error of SH band (plain least squares)")
    np.atleast_1d(axes)[-1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path = out_dir / "stability_lighting.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    written.append(path)

    brdf = [r for r in rows if r["problem"] == "BRDF estimation"]
    quantities = list(dict.fromkeys(r["quantity"] for r in brdf))
    fig, axes = plt.subplots(1, len(quantities), figsize=(5.5 * len(quantities), 4.2))
    for ax, q in zip(np.atleast_1d(axes), quantities):
        for scene in dict.fromkeys(r["scene"] for r in brdf):
            pts = [r for r in brdf if r["scene"] == scene and r["quantity"] == q]
            noise = _noise_axis(np.array([r["noise"] for r in pts]))
            ax.loglog(noise, np.maximum([r["relative_error"] for r in pts], 1e-6), marker="o", label=scene)
        ax.set_title(f"BRDF estimation: {q}")
        ax.set_xlabel("noise (fraction of mean radiance; leftmost = noiseless)")
        ax.set_ylabel("error")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = out_dir / "stability_brdf.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    written.append(path)
    return written


def _write_csv(path: Path, rows: list[dict]) -> Path:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


# --------------------------------------------------------------------------------------- suites


def stability_suite(quick: bool, repeat: int, output: Path = Path("bench")) -> list:
    """`sigrend bench stability`: the charts and CSV in ``output``; rows = error at each noise level.

    ``repeat`` is unused (errors, not timings); ``quick`` runs one trial per noise level.
    """
    out_dir = Path(output)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    trials = 1 if quick else 3
    rows = stability_lighting(rng, trials=trials) + stability_brdf(rng, trials=trials)
    _write_csv(out_dir / "stability.csv", rows)
    charts = plot_stability(rows, out_dir)
    keep = [r for r in rows if r["noise"] in (0.0, 0.01, 0.1)]
    return [
        BenchRow(
            f"{r['scene']}: {r['quantity']}", 0, f"noise {r['noise']:g}", r["relative_error"], "relative error", r["problem"]
        )
        for r in keep
    ] + [BenchRow("charts", 0, "", len(charts), "files", ", ".join(str(p) for p in charts))]


# --------------------------------------------------------------------------------------- pipeline suite

SCENES = {
    "diffuse": "lambert:albedo=0.6,0.5,0.4",
    "glossy": "principled:base_color=0.5,0.35,0.2,roughness=0.3",
}
REPORT_BANDS = 4  # lighting error columns band0 .. band4


def _lighting_band_errors(fitted: np.ndarray, truth: np.ndarray, scale_free: bool) -> tuple[np.ndarray, float]:
    """Relative error per band (l <= REPORT_BANDS) of fitted vs true SH lighting; bands the fit does not
    have count as error 1.  ``scale_free``: first fit the one global scale (factorization)."""
    ref = truth[: num_coeffs(REPORT_BANDS)]
    est = fitted[: len(ref)]  # band_relative_errors counts the rows it lacks as zero
    scale = float((est * ref[: len(est)]).sum() / (est * est).sum()) if scale_free and (est**2).sum() > 0 else 1.0
    return band_relative_errors(scale * est, ref), scale


def _pareto(times: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Mask of the configurations no other one beats in both time and error."""
    front = np.ones(len(times), bool)
    for i in range(len(times)):
        better = (times <= times[i]) & (errors <= errors[i]) & ((times < times[i]) | (errors < errors[i]))
        front[i] = not better.any()
    return front


def pipeline_configs(quick: bool) -> list[dict]:
    """The sweep on the physical fit: per scene and fit mode, the lighting's SH order (an integer:
    that order only; 'auto': material chosen at order 8, lighting refitted up to 16) at the full
    data, plus 'auto' on a third of the fit's samples, on every 3rd pixel and on 4 training views."""
    orders = ("4", "auto") if quick else ("2", "4", "8", "auto")
    configs = []
    for scene in SCENES:
        for mode in ("known BRDF", "factorization"):
            for order in orders:
                configs.append(
                    {"scene": scene, "mode": mode, "order": order, "train_views": 9, "stride": 1, "fit_samples": 30000}
                )
            if not quick:
                configs.append(
                    {"scene": scene, "mode": mode, "order": "auto", "train_views": 9, "stride": 1, "fit_samples": 10000}
                )
                configs.append(
                    {"scene": scene, "mode": mode, "order": "auto", "train_views": 9, "stride": 3, "fit_samples": 30000}
                )
                configs.append(
                    {"scene": scene, "mode": mode, "order": "auto", "train_views": 4, "stride": 1, "fit_samples": 30000}
                )
    return configs


def run_pipeline_bench(out_dir: Path, quick: bool = False) -> tuple[list[dict], list[Path]]:
    """Render the scenes, run samples -> fit -> relight per configuration; write bench.csv + bench.png."""
    out_dir = Path(out_dir)
    scratch = out_dir / "pipeline_scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    rows, sample_runs = [], {}
    for config in pipeline_configs(quick):
        capture, validation, sample_work, samples_s = _bench_samples(scratch, config, quick, sample_runs)
        name = (
            f"{config['scene']}_{config['mode'].replace(' ', '-')}_L{config['order']}_v{config['train_views']}"
            f"_s{config['stride']}_n{config['fit_samples']}"
        )
        row = _bench_fit_relight(config, capture, scratch / config["scene"] / name, sample_work, validation, samples_s)
        rows.append(row)
        print(f"{name}: time {row['time_s']:.2f} s, relight error {100 * row['relight_error']:.2f}%")
    mark_pareto(rows)
    csv_path = _write_csv(out_dir / "bench.csv", rows)
    png = plot_pareto(rows, out_dir / "bench.png")
    if not quick:
        shutil.rmtree(scratch, ignore_errors=True)
    return rows, [csv_path, png]


def _bench_samples(scratch: Path, config: dict, quick: bool, runs: dict) -> tuple[Path, list[str], Path, float]:
    """A configuration's scene rendered (once) and its training views' samples (once per views and
    stride; ``runs`` caches them) -> (capture, the validation views, the samples' work folder, the
    samples stage's seconds).  Every fourth view is held out for validation."""
    scene = config["scene"]
    views, size = 12, (64, 64) if quick else (96, 96)
    capture = scratch / scene / "capture"
    if not capture.exists():
        make_test_capture(capture, brdf=SCENES[scene], env="area", views=views, size=size, fmt="exr", mesh="sphere", noise="none")
    keys = sorted(f"{i:04d}.exr" for i in range(views))
    validation = keys[3::4]
    training = [k for k in keys if k not in validation]
    train = training[:: max(1, len(training) // config["train_views"])][: config["train_views"]]
    key = (scene, config["train_views"], config["stride"])
    if key not in runs:
        work = scratch / scene / f"samples_v{config['train_views']}_s{config['stride']}"
        holdout = tuple(sorted(set(keys) - set(train)))
        result = run_stage(
            "samples", capture=capture, work=work, settings=stage_settings("samples", holdout=holdout, stride=config["stride"])
        )
        runs[key] = (work, result.seconds)
    return (capture, validation) + runs[key]


def _bench_fit_relight(
    config: dict, capture: Path, work: Path, sample_work: Path, validation: list[str], samples_s: float
) -> dict:
    """The fit of one configuration on the shared samples (hard-linked into ``work``) and its relight
    of the validation views -> bench.csv's row: times, relight error, lighting scale and band errors,
    the fitted order, model and roughness."""
    work.mkdir(parents=True, exist_ok=True)
    if not (work / "samples.npz").exists():
        os.link(sample_work / "samples.npz", work / "samples.npz")
    brdf = str(capture / "gt" / "brdf.json") if config["mode"] == "known BRDF" else "auto"
    fit = run_stage(
        "fit",
        capture=capture,
        work=work,
        settings=stage_settings(
            "fit", brdf=brdf, order=config["order"], lighting="unknown", physical_samples=config["fit_samples"]
        ),
    )
    relit = run_stage(
        "relight",
        capture=capture,
        work=work,
        settings=stage_settings("relight", views=",".join(validation), compare=True, supersample=1),
    )
    check = json.loads((work / "relight" / "relight.json").read_text())["compare"]
    fitted = read_lighting_sh(work / "fit" / "lighting_sh.json")
    brdf_fit = json.loads((work / "fit" / "brdf.json").read_text())
    band_err, scale = _lighting_band_errors(
        fitted, read_lighting_sh(capture / "gt" / "lighting_sh.json"), config["mode"] != "known BRDF"
    )
    return {
        **config,
        "samples_s": round(samples_s, 3),
        "fit_s": round(fit.seconds, 3),
        "time_s": round(samples_s + fit.seconds, 3),
        "relight_s": round(relit.seconds, 3),
        "relight_error": check["relative_error"],
        "lighting_scale": scale,
        "fitted_order": order_of(fitted.shape[0]),
        "fitted_model": brdf_fit["model"],
        "fitted_roughness": brdf_fit.get("roughness", ""),
        **{f"band{l}_error": float(e) for l, e in enumerate(band_err)},
    }


def mark_pareto(rows: list[dict]) -> None:
    """Set ``row["pareto"]``: on the speed/accuracy front of its scene (fronts across scenes mean nothing)."""
    for scene in dict.fromkeys(r["scene"] for r in rows):
        sub = [r for r in rows if r["scene"] == scene]
        front = _pareto(np.array([r["time_s"] for r in sub]), np.array([r["relight_error"] for r in sub]))
        for r, f in zip(sub, front):
            r["pareto"] = bool(f)


ORDER_COLOUR = {"auto": 16}  # 'auto' ends at orders up to --max-order 16


def plot_pareto(rows: list[dict], path: Path) -> Path:
    """bench.png: relight error on held-out views against time (samples + fit), one panel per scene,
    each scene's Pareto front marked."""
    plt = _plt()
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(1, len(scenes), figsize=(6 * len(scenes), 4.8))
    markers = {"known BRDF": "o", "factorization": "s"}
    for ax, scene in zip(np.atleast_1d(axes), scenes):
        sub = [r for r in rows if r["scene"] == scene]
        for r in sub:
            colour = plt.cm.viridis(min(int(ORDER_COLOUR.get(r["order"], r["order"])), 16) / 17)
            ax.scatter(
                r["time_s"],
                r["relight_error"] * 100,
                marker=markers[r["mode"]],
                color=colour,
                s=50,
                edgecolors="k" if r["pareto"] else "none",
                linewidths=1.2,
            )
            ax.annotate(
                f"L{r['order']} v{r['train_views']} s{r['stride']} n{r['fit_samples'] // 1000}k",
                (r["time_s"], r["relight_error"] * 100),
                fontsize=6,
                xytext=(3, 3),
                textcoords="offset points",
            )
        front = sorted((r["time_s"], r["relight_error"] * 100) for r in sub if r["pareto"])
        if front:
            ax.step(*zip(*front), where="post", color="k", lw=1, ls="--", label="Pareto front")
        for mode, m in markers.items():
            ax.scatter([], [], marker=m, color="gray", label=mode)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time: samples + fit (s, 2 shared cores)")
        ax.set_ylabel("relight error on held-out views (%, relative RMS)")
        ax.set_title(
            f"{scene} scene (colour = SH order L; v = training views, s = sample stride, n = samples fitted)", fontsize=8
        )
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def pipeline_suite(quick: bool, repeat: int, output: Path = Path("bench")) -> list:
    """`sigrend bench pipeline`: bench.csv + bench.png in ``output``; rows = each configuration's numbers.

    ``repeat`` is unused (each configuration runs once: its time is part of the result)."""
    Path(output).mkdir(parents=True, exist_ok=True)
    rows, written = run_pipeline_bench(Path(output), quick=quick)
    out = []
    for r in rows:
        case = f"{r['scene']} {r['mode']}"
        size = f"v{r['train_views']} s{r['stride']} n{r['fit_samples']}"
        note = "pareto" if r["pareto"] else ""
        out.append(BenchRow(case, r["fitted_order"], size, r["time_s"], "s (samples+fit)", note))
        out.append(BenchRow(case, r["fitted_order"], size, r["relight_error"], "relight error", note))
    return out + [BenchRow("outputs", 0, "", len(written), "files", ", ".join(str(p) for p in written))]
