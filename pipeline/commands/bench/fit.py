"""`sigrend bench fit`: fit time vs number of samples (10^4 ... 10^7) and vs SH order, per mode.

Samples are synthetic (random normals, cameras in the normals' hemisphere, radiance from the
forward model), grouped by image as in a samples file; up to 10^6 they are generated before the
timed call, at 10^7 chunk by chunk inside it (memory O(chunk); the time then includes generation).  Cases:
  lighting (known BRDF)  chunked normal equations + per-band solve (Lambert: one shared Gram;
                         microfacet: one Gram per channel), order 8 vs N, and vs order at N = 10^5
  brdf (known lighting)  variable projection (Brent over roughness + NNLS) on N in-memory samples
  factorization          joint linear start + 3 alternations, microfacet, order 8
Target (issue 6): Lambert lighting at order 8 from 10^6 samples well under 2 s on 2 cores.
OpenBLAS threads fight other processes for the 2 cores: OPENBLAS_NUM_THREADS=1 is often faster.
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.commands.bench import BenchRow, best_time
from pipeline.core import forward, solve
from pipeline.core.brdf import Brdf
from pipeline.core.factorization import ConvexOptions, brdf_data, factorize, fit_brdf_models
from pipeline.core.forward import render_samples

CHUNK = 262144
LAMBERT = Brdf("lambert", albedo=(0.6, 0.5, 0.4))
GLOSSY = Brdf("microfacet", albedo=(0.3, 0.25, 0.2), f0=(0.9, 0.9, 0.9), beckmann_sigma=0.15)


def _chunk(rng: np.random.Generator, n: int, truth: np.ndarray, brdf: Brdf) -> dict:
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    view = normal + 0.5 * rng.normal(size=(n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    return {
        "normal": normal,
        "view_dir": view,
        "radiance": render_samples(truth, brdf, normal, view),
        "image_id": np.sort(rng.integers(0, 32, n)),
        "weight": np.ones(n),
    }  # grouped by image, as in a file


def _chunks(n: int, truth: np.ndarray):
    """The samples in chunks, generated on the fly (so 10^7 stays O(chunk) in memory)."""
    rng = np.random.default_rng(0)
    for start in range(0, n, CHUNK):
        yield _chunk(rng, min(CHUNK, n - start), truth, LAMBERT)  # radiance content does not change the cost


def _lighting_fit(chunks, order: int, brdf: Brdf) -> None:
    with_lobe = brdf.has_lobe
    eqs = solve.NormalEquations(order, 4, shared=not with_lobe)
    for c in chunks:
        terms = forward.design_terms(c["normal"], c["view_dir"], order, with_lobe)
        designs = terms.diffuse[None] if not with_lobe else forward.channel_designs(terms, brdf, order)
        eqs.add(designs, c["radiance"], c["weight"], c["image_id"] % 4)
    g, h, btb, w = eqs.channel_system(slice(None), np.asarray(brdf.albedo) if eqs.shared else None)
    solve.solve_lighting(g, h, btb, w, int(eqs.count.sum()), order, independent_groups=32)


def _timed_fit(n: int, order: int, brdf: Brdf, truth: np.ndarray, repeat: int) -> tuple[float, float, str]:
    """(wall s, cpu s, note): samples pre-generated up to 10^6, streamed (generation included) beyond."""
    if n <= 10**6:
        chunks = list(_chunks(n, truth))
        return (
            best_time(lambda: _lighting_fit(chunks, order, brdf), repeat),
            _cpu_seconds(lambda: _lighting_fit(chunks, order, brdf)),
            "samples in memory",
        )
    return (
        best_time(lambda: _lighting_fit(_chunks(n, truth), order, brdf), 1),
        _cpu_seconds(lambda: _lighting_fit(_chunks(n, truth), order, brdf)),
        "streamed chunks, time includes generating them",
    )


def _cpu_seconds(func) -> float:
    start = time.process_time()
    func()
    return time.process_time() - start


def fit_suite(quick: bool, repeat: int) -> list[BenchRow]:
    rng = np.random.default_rng(1)
    truth8 = rng.normal(size=(81, 3)) * 0.1
    truth8[0] = 3.0
    rows = []
    sizes = (10**4, 10**5) if quick else (10**4, 10**5, 10**6, 10**7)
    for n in sizes:
        for name, brdf in (("lighting lambert", LAMBERT), ("lighting microfacet", GLOSSY)):
            if brdf is GLOSSY and n >= 10**7:
                continue
            wall, cpu, note = _timed_fit(n, 8, brdf, truth8, repeat)
            rows.append(BenchRow(name, 8, f"{n} samples", wall, "s", f"normal equations + solve; {note}"))
            rows.append(
                BenchRow(
                    name + " (cpu)",
                    8,
                    f"{n} samples",
                    cpu,
                    "cpu s",
                    "process CPU time = wall time on idle cores when BLAS runs one thread",
                )
            )
    n = 10**4 if quick else 10**5
    for order in (2, 4, 8, 12, 16):
        truth = np.zeros(((order + 1) ** 2, 3))
        truth[0] = 3.0
        wall, _, note = _timed_fit(n, order, LAMBERT, truth, repeat)
        rows.append(BenchRow("lighting lambert", order, f"{n} samples", wall, "s", f"vs order; {note}"))
    opts = ConvexOptions(iterations=3)
    for n in (2000,) if quick else (10**4, 10**5):
        data = _chunk(np.random.default_rng(2), n, truth8, GLOSSY)
        seconds = best_time(lambda: fit_brdf_models(brdf_data(data, truth8, 4), ["microfacet"], opts, 8), 1)
        rows.append(
            BenchRow("brdf microfacet", 8, f"{n} samples", seconds, "s", "variable projection, 4-fold validation + full fit")
        )
        seconds = best_time(lambda: factorize(data, "microfacet", 8, np.full(3, 0.5), opts), 1)
        rows.append(
            BenchRow(
                "factorization microfacet", 8, f"{n} samples", seconds, "s", "joint linear start (9 widths) + 3 alternations"
            )
        )
    return rows
