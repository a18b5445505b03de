"""`sigrend bench synth`: seconds per view of the reference renderer (pipeline.core.render) on the
Stanford bunny, with and without shadows, first view / second view / cached visibility."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from pipeline.commands.bench import BenchRow
from pipeline.core.brdf import Brdf
from pipeline.core.procedural_envmaps import make_envmap
from pipeline.core.render import Renderer
from pipeline.core.render_view import render_view
from pipeline.raycast import ray_mesh
from pipeline.synth import SynthSettings, load_mesh, make_views

BENCH_MESH = Path(__file__).resolve().parents[3] / "sample_data" / "meshes" / "stanford-bunny.obj"  # see its SOURCES.md


def synth_suite(quick: bool, repeat: int) -> list:
    """Seconds per 512 x 512 view of the bunny under a 128 x 64 env: Lambert / microfacet, +- shadows.

    Per case three numbers: the first view (includes the shadow rays of the vertices it sees),
    a second view from another side (shadow rays for the newly seen vertices only), and a repeat
    of the first view (shading only: visibility is cached per scene).  The mesh is the Stanford
    bunny (``BENCH_MESH``, else the 'sphere'); --quick renders 128 x 128.
    """
    mesh_spec = str(BENCH_MESH) if BENCH_MESH.is_file() else "sphere"
    mesh = load_mesh(mesh_spec, 0.2, "y")
    size = 128 if quick else 512
    settings = replace(SynthSettings(), views=2, size=(size, size), layout="ring", elevation=(20.0, 40.0))
    camera, poses = make_views(mesh, settings, None)
    env = make_envmap("area", 64, n=3)
    brdfs = {
        "lambert": Brdf("lambert", albedo=(0.5, 0.5, 0.5)),
        "microfacet": Brdf("microfacet", albedo=(0.2, 0.3, 0.5), f0=0.04, beckmann_sigma=0.2),
    }
    rows = []
    for name, brdf in brdfs.items():
        for shadows in (False, True):
            renderer = Renderer(ray_mesh(mesh), env, brdf, shadows=shadows)
            case = f"{name} {'shadows' if shadows else 'no shadows'}"
            note = f"{Path(mesh_spec).name}, {len(renderer.lights)} light directions, 128x64 env"
            for label, pose in (("first view", poses[0]), ("second view", poses[1])):
                start = time.perf_counter()
                render_view(renderer, camera, *pose)
                rows.append(BenchRow(f"{case}, {label}", 0, f"{size}x{size}", time.perf_counter() - start, "s/view", note))
            best = min(_timed(lambda: render_view(renderer, camera, *poses[0])) for _ in range(max(1, repeat)))
            rows.append(BenchRow(f"{case}, cached visibility", 0, f"{size}x{size}", best, "s/view", note))
    return rows


def _timed(func) -> float:
    start = time.perf_counter()
    func()
    return time.perf_counter() - start
