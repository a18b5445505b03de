"""The interreflection proxy (pipeline/proxy.py, issue 47 item 1): small meshes exactly as without
it, a forced proxy within a stated tolerance of the full computation; and the soft shadows of a
dense stream of samples (prt.over_chunks), within a stated tolerance of the exact ones."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.core import prt
from pipeline.core.interreflection import indirect_transfer
from pipeline.io.mesh import read_mesh
from pipeline.proxy import build_proxy, proxy_faces, with_proxy
from pipeline.raycast import ray_mesh

MESH = Path(__file__).resolve().parents[1] / "sample_data" / "capture" / "mesh.ply"
SKY = np.zeros((25, 3))
SKY[0], SKY[2], SKY[3] = 1.0, 0.8, 0.3  # SH lighting brighter above, a little from +x


def _points(mesh, n: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    faces = rng.integers(0, len(mesh.faces), n)
    return faces, rng.dirichlet([1.0, 1.0, 1.0], n), np.asarray(mesh.face_normals)[faces]


def _radiance(rm, faces, bary, view, seed: int = 0):
    """(direct, interreflected) irradiance (N, 3) under SKY at base colour 0.8, SH order 4."""
    g = prt.geometry(rm, faces, bary, view, 4, seed=seed)
    indirect = indirect_transfer(g, None, np.array([0.8, 0.8, 0.8]))
    return g.direct @ SKY, np.einsum("pkc,kc->pc", indirect, SKY)


def test_a_mesh_coarser_than_the_threshold_gets_no_proxy_and_the_same_numbers():
    """sample_data's mesh (5856 faces) at a 1 mm footprint: 2-pixel edges (the default) need 45 k faces, more than
    half its own, so no proxy, and the transfer and interreflection are byte-identical to the plain
    RayMesh's; a proxy forced on the same mesh (8-pixel edges, no threshold) does change them (the
    comparison can fail)."""
    mesh = read_mesh(MESH)
    assert proxy_faces(float(mesh.area), 2e-3) > len(mesh.faces) / 2
    rm = with_proxy(mesh, 1e-3)
    assert rm.proxy is None
    pts = _points(mesh, 1500)
    plain = _radiance(ray_mesh(mesh), *pts)
    same = _radiance(rm, *pts)
    assert all(np.array_equal(a, b) for a, b in zip(plain, same))
    forced = with_proxy(mesh, 1e-3, pixels=8.0, min_ratio=0.0)
    assert forced.proxy is not None and len(forced.proxy.mesh.faces) < len(mesh.faces)
    assert not np.array_equal(_radiance(forced, *pts)[1], plain[1])


@pytest.mark.slow  # 3 s: the interreflection of 3000 points on a 23 k-face mesh, twice
def test_a_proxy_gives_the_full_meshs_interreflection_within_its_monte_carlo_noise():
    """sample_data's mesh subdivided once (23 k faces) with a proxy simplified back to 5856 faces:
    the direct irradiance at 3000 points stays on the full mesh (its points' own shadow rays with a
    proxy, Renderer.point_rays: within 0.5 % RMS of the vertices' visibility, measured 0.13 %,
    test_point_rays_agree_with_the_vertices_visibility) and the interreflected part — 7 % of the total
    here — differs from the full
    computation's by at most 4 % of the total radiance's RMS per point (measured 2.8 %; two seeds of
    the full computation differ by 1.5 %, its 64-ray Monte Carlo noise) and by at most 10 % in its mean
    (measured +6 %: the simplified surface's bounces)."""
    fine = read_mesh(MESH).subdivide()
    rm = ray_mesh(fine)
    pts = _points(fine, 3000)
    direct, indirect = _radiance(rm, *pts)
    proxied = replace(rm, proxy=build_proxy(rm, 5856))
    p_direct, p_indirect = _radiance(proxied, *pts)
    assert np.sqrt(np.mean((p_direct - direct) ** 2)) < 0.005 * np.sqrt(np.mean(direct**2))
    scale = np.sqrt(np.mean((direct + indirect) ** 2))
    assert 0.03 < indirect.mean() / direct.mean() < 0.15  # there is interreflection to get right
    assert np.sqrt(np.mean((p_indirect - indirect) ** 2)) / scale < 0.04
    assert abs(p_indirect.mean() / indirect.mean() - 1.0) < 0.10


def test_point_rays_agree_with_the_vertices_visibility():
    """With a proxy the samples' direct transfer takes its visibility from a shadow ray at each sample
    (Renderer.point_rays, prt.geometry) instead of its triangle's three vertices' (rays only where they
    disagree).  On sample_data's mesh (5856 faces, a proxy forced at a quarter of them) at 3000 points,
    SH order 4, the direct irradiance under SKY agrees with the vertices' to 0.5 % of its RMS (measured
    0.15 %), in its mean to 0.2 % (measured -0.05 %) and at every point to 5 % (measured 2.2 %: a point
    beside a shadow edge that its vertices' lifted rays see otherwise); the interreflection, which takes
    no sample visibility, is the same array."""
    mesh = read_mesh(MESH)
    rm = ray_mesh(mesh)
    proxied = replace(rm, proxy=build_proxy(rm, len(mesh.faces) // 4))
    pts = _points(mesh, 3000)
    plain = prt.geometry(rm, *pts, 4)  # no proxy: the vertices' visibility
    rays = prt.geometry(proxied, *pts, 4)
    assert rays.renderer.point_rays and not plain.renderer.point_rays
    vertex, point = plain.direct @ SKY, rays.direct @ SKY
    rms = np.sqrt(np.mean(vertex**2))
    assert np.sqrt(np.mean((point - vertex) ** 2)) < 0.005 * rms
    assert abs(point.mean() / vertex.mean() - 1.0) < 0.002
    assert np.abs(point - vertex).max() < 0.05 * rms
    assert not np.array_equal(point, vertex)  # the two paths differ (the comparison can fail)


def test_a_dense_stream_takes_soft_shadows_close_to_the_exact_ones(monkeypatch):
    """prt.over_chunks on more than DENSE_SAMPLES samples per vertex (here 8: sample_data's mesh has 3225
    vertices, 30 000 points) interpolates its vertices' visibility instead of casting a shadow ray where they
    disagree (Renderer._soft_visibility).  Where a point's three vertices agree on a direction the two
    visibilities are the same; over all points the direct irradiance under SKY is within 3 % of its RMS
    (measured 0.67 %) and its mean within 0.5 % (measured +0.07 %) of the exact one; a stream of fewer
    samples per vertex keeps the exact shadows."""
    monkeypatch.setattr(prt, "DENSE_SAMPLES", 8)
    mesh = read_mesh(MESH)
    geo = prt.geometry(ray_mesh(mesh), *_points(mesh, 100), 4)
    faces, bary, view = _points(mesh, 30000, seed=2)
    assert len(faces) > prt.DENSE_SAMPLES * len(mesh.vertices)

    def irradiance(g):
        return (g.direct @ SKY,)

    (soft,) = prt.over_chunks(geo, faces, bary, view, irradiance)
    points = prt.geometry_at(geo, faces, bary, view)
    (exact,) = irradiance(points)
    (few,) = prt.over_chunks(geo, faces[:20000], bary[:20000], view[:20000], irradiance)
    r, tri = geo.renderer, np.asarray(mesh.faces)[faces]
    vis = r._visibility[tri]  # (N, 3, D)
    agree = (vis == vis[:, :1]).all(axis=1)
    assert 0.5 < agree.mean() < 0.99  # pairs both ways
    weights = r._soft_visibility(tri, bary)
    np.testing.assert_allclose(weights[agree], r._point_visibility(faces, tri, bary)[agree], atol=1e-6)
    rms = np.sqrt(np.mean(exact**2))
    assert np.sqrt(np.mean((soft - exact) ** 2)) < 0.03 * rms
    assert abs(soft.mean() / exact.mean() - 1.0) < 0.005
    assert not np.array_equal(soft, exact)  # the two paths differ (the comparison can fail)
    np.testing.assert_array_equal(few, exact[:20000])


def _work_with_samples(tmp_path, mesh, focal: float, n: int = 2000):
    """A capture (mesh.ply, poses.json: 4 cameras 0.5 m from the origin, focal ``focal`` px) and a work
    folder whose samples.npz has ``n`` samples on random faces of ``mesh`` seen by those cameras."""
    from pipeline.core.camera import Camera, Rigid3, look_at
    from pipeline.io.poses import ImagePose, Poses, write_poses
    from pipeline.io.samples import write_samples

    capture, work = tmp_path / "cap", tmp_path / "work"
    capture.mkdir(parents=True)
    work.mkdir(parents=True)
    mesh.export(capture / "mesh.ply")
    poses = Poses()
    poses.cameras["cam0"] = Camera("PINHOLE", 512, 512, (focal, focal, 256.0, 256.0))
    centre = np.asarray(mesh.bounds).mean(axis=0)
    for i in range(4):
        phi = np.pi * i / 2
        R, t = look_at(centre + 0.5 * np.array([np.cos(phi), np.sin(phi), 0.3]), centre)
        poses.images[f"{i:04d}.exr"] = ImagePose("cam0", Rigid3(R, t))
    write_poses(capture / "poses.json", poses)
    faces, bary, normals = _points(mesh, n)
    z3 = np.zeros((n, 3))
    arrays = {
        "point": z3,
        "normal": normals,
        "view_dir": normals,
        "radiance": z3 + 0.5,
        "image_id": np.arange(n) % 4,
        "pixel": np.zeros((n, 2)),
        "face": faces,
        "bary": bary,
        "weight": np.ones(n),
        "visibility": np.ones(n),
        "image_keys": list(poses.images),
    }
    write_samples(work / "samples.npz", arrays, {"count": n})
    return capture, work


def test_relight_builds_the_fits_proxy_where_the_mesh_is_finer_than_the_photos(tmp_path):
    """stages.relight.scene_rays with --proxy-pixels 2: sample_data's mesh subdivided once (23 k faces)
    seen by 512 px cameras of focal 100 px at 0.5 m (about 5 mm per pixel: 2-pixel edges need far fewer
    faces) gets a proxy, the same as the fit's with_proxy at the samples' footprint; at focal 5000 px
    (0.1 mm per pixel), with the default --proxy-pixels 0, the frequency method or without samples.npz,
    none."""
    from pipeline.io.poses import read_poses
    from pipeline.proxy import samples_footprint_m
    from pipeline.settings import make_settings
    from stages import relight

    fine = read_mesh(MESH).subdivide()
    capture, work = _work_with_samples(tmp_path / "coarse", fine, 100.0)
    settings = make_settings(relight.Settings, proxy_pixels=2.0)
    assert make_settings(relight.Settings).proxy_pixels == 0  # opt-in: relight renders as before by default
    rm = relight.scene_rays(fine, capture, work, settings)
    assert rm.proxy is not None and len(rm.proxy.mesh.faces) < len(fine.faces) / 2
    faces, bary, _ = _points(fine, 2000)
    data = {"face": faces, "bary": bary, "image_id": np.arange(2000) % 4}
    footprint = samples_footprint_m(
        fine.triangles, data, read_poses(capture / "poses.json"), ["0000.exr", "0001.exr", "0002.exr", "0003.exr"]
    )
    assert len(rm.proxy.mesh.faces) == len(with_proxy(fine, footprint).proxy.mesh.faces)
    assert relight.Path(work / "samples.npz") in relight.inputs(capture=capture, work=work, settings=settings)
    for other in (make_settings(relight.Settings), make_settings(relight.Settings, proxy_pixels=2.0, method="frequency")):
        assert relight.scene_rays(fine, capture, work, other).proxy is None
    sharp = _work_with_samples(tmp_path / "sharp", fine, 5000.0)
    assert relight.scene_rays(fine, *sharp, settings).proxy is None
    (work / "samples.npz").unlink()
    assert relight.scene_rays(fine, capture, work, settings).proxy is None
