"""`sigrend bench fit`: fit time vs number of samples (10^4 ... 10^7) and vs SH order, per mode.

Samples are synthetic (random normals, cameras in the normals' hemisphere, radiance from the
forward model) and generated chunk by chunk inside the timed call, as a samples file would be
streamed, so memory stays O(chunk) at 10^7.  Cases:
  lighting (known BRDF)  chunked normal equations + per-band solve (Lambert: one shared Gram;
                         microfacet: one Gram per channel), order 8 vs N, and vs order at N = 10^5
  brdf (known lighting)  variable projection (nlopt over roughness + NNLS) on N in-memory samples
  factorization          joint linear start + 3 alternations, microfacet, order 8
Target (issue 6): Lambert lighting at order 8 from 10^6 samples well under 2 s on 2 cores.
OpenBLAS threads fight other processes for the 2 cores: OPENBLAS_NUM_THREADS=1 is often faster.
"""

from __future__ import annotations

import numpy as np

from pipeline.commands.bench import BenchRow, best_time

CHUNK = 262144
LAMBERT = {"model": "lambert", "albedo": [0.6, 0.5, 0.4]}
GLOSSY = {"model": "microfacet", "albedo": [0.3, 0.25, 0.2], "specular": [0.9, 0.9, 0.9], "roughness": 0.15}


def _chunk(rng: np.random.Generator, n: int, truth: np.ndarray, brdf: dict) -> dict:
    from pipeline.core.forward import render_samples

    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    view = normal + 0.5 * rng.normal(size=(n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    return {"normal": normal, "view_dir": view, "radiance": render_samples(truth, brdf, normal, view),
            "image_id": np.sort(rng.integers(0, 32, n)), "weight": np.ones(n)}   # grouped by image, as in a file


def _lighting_fit(n: int, order: int, brdf: dict, truth: np.ndarray) -> None:
    from pipeline.core import forward, solve

    rng = np.random.default_rng(0)
    with_lobe = brdf["model"] in forward.LOBE_MODELS
    eqs = solve.NormalEquations(order, 4, shared=not with_lobe)
    for start in range(0, n, CHUNK):
        c = _chunk(rng, min(CHUNK, n - start), truth, LAMBERT)  # radiance content does not change the cost
        terms = forward.design_terms(c["normal"], c["view_dir"], order, with_lobe)
        designs = terms.diffuse[None] if not with_lobe else forward.channel_designs(terms, brdf, order)
        eqs.add(designs, c["radiance"], c["weight"], c["image_id"] % 4)
    g, h, btb, w = eqs.channel_system(slice(None), np.asarray(brdf["albedo"]) if eqs.shared else None)
    solve.solve_lighting(g, h, btb, w, int(eqs.count.sum()), order, independent_groups=32)


def _generation_only(n: int, truth: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    for start in range(0, n, CHUNK):
        _chunk(rng, min(CHUNK, n - start), truth, LAMBERT)


def fit_suite(quick: bool, repeat: int) -> list[BenchRow]:
    from pipeline.settings import make_settings
    from stages import fit

    rng = np.random.default_rng(1)
    truth8 = rng.normal(size=(81, 3)) * 0.1
    truth8[0] = 3.0
    rows = []
    sizes = (10 ** 4, 10 ** 5) if quick else (10 ** 4, 10 ** 5, 10 ** 6, 10 ** 7)
    for n in sizes:
        reps = 1 if n >= 10 ** 7 else repeat
        gen = best_time(lambda: _generation_only(n, truth8), reps)
        for name, brdf in (("lighting lambert", LAMBERT), ("lighting microfacet", GLOSSY)):
            if brdf is GLOSSY and n >= 10 ** 7:
                continue
            total = best_time(lambda: _lighting_fit(n, 8, brdf, truth8), reps)
            rows.append(BenchRow(name, 8, f"{n} samples", total - gen, "s",
                                 f"normal equations + solve, excluding {gen:.2f} s of sample generation"))
    n = 10 ** 4 if quick else 10 ** 5
    gen = best_time(lambda: _generation_only(n, truth8), repeat)
    for order in (2, 4, 8, 12, 16):
        truth = np.zeros(((order + 1) ** 2, 3))
        truth[0] = 3.0
        seconds = best_time(lambda: _lighting_fit(n, order, LAMBERT, truth), repeat) - gen
        rows.append(BenchRow("lighting lambert", order, f"{n} samples", seconds, "s", "vs order"))
    settings = make_settings(fit.Settings, iterations=3)
    for n in ((2000,) if quick else (10 ** 4, 10 ** 5)):
        data = _chunk(np.random.default_rng(2), n, truth8, GLOSSY)
        seconds = best_time(lambda: fit.fit_brdf_models(fit.brdf_data(data, truth8, 4), ["microfacet"], settings, 8), 1)
        rows.append(BenchRow("brdf microfacet", 8, f"{n} samples", seconds, "s",
                             "variable projection, 4-fold validation + full fit"))
        seconds = best_time(lambda: fit.factorize(data, "microfacet", 8, np.full(3, 0.5), settings), 1)
        rows.append(BenchRow("factorization microfacet", 8, f"{n} samples", seconds, "s",
                             "joint linear start (9 widths) + 3 alternations"))
    return rows
