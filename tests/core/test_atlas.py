"""The UV atlas (pipeline.core.atlas, pipeline.unwrap): conventions checked against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from helpers import segfault

from pipeline.core import atlas as atlas_mod
from pipeline.unwrap import UnwrapFailed, in_child, unwrap


@pytest.fixture(scope="module")
def sphere_atlas():
    mesh = trimesh.creation.icosphere(subdivisions=3)  # radius 1, area ~ 4 pi
    return mesh, unwrap(mesh.vertices, mesh.faces, texel_m=0.02)


def test_unwrap_keeps_faces_and_the_texel_size(sphere_atlas):
    """xatlas's atlas keeps the mesh's faces in order (one UV per face corner, all in [0, 1]) and packs
    them at the asked texel size: the texels whose centre falls in a chart cover the surface's area
    within 10 % (area / texel^2 = 31 400 texels for a unit sphere at 0.02; charts' rasterization
    loses or gains a fraction of a texel along each chart's boundary)."""
    mesh, atlas = sphere_atlas
    assert atlas.face_uv.shape == (len(mesh.faces), 3, 2)
    assert atlas.face_uv.min() >= 0.0 and atlas.face_uv.max() <= 1.0
    texel, _, _ = atlas_mod.texel_points(atlas)
    assert len(texel) * 0.02**2 == pytest.approx(mesh.area, rel=0.10)


def test_small_faces_keep_their_uv_area():
    """A 2 cm object in metres whose faces are ~0.06 mm^2 (as a scan of a walnut at 30k faces): every face keeps
    a UV area in proportion to its surface area (xatlas collapses faces under FLT_EPSILON in its units, i.e.
    under 0.12 mm^2 when given metres: unwrap hands it texel units), and the texels cover the surface."""
    mesh = trimesh.creation.icosphere(subdivisions=5)  # 20 480 faces
    mesh.apply_scale(0.01)  # radius 1 cm: mean face area 0.061 mm^2
    texel_m = 5e-5
    atlas = unwrap(mesh.vertices, mesh.faces, texel_m=texel_m)
    uv = atlas.face_uv * [atlas.width, atlas.height]  # texels
    a, b = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    uv_area = 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    ratio = uv_area * texel_m**2 / mesh.area_faces
    assert mesh.area_faces.max() < 1.19e-7  # every face below xatlas's epsilon in metres
    assert np.percentile(ratio, 1) > 0.5 and np.median(ratio) == pytest.approx(1.0, rel=0.2), np.percentile(ratio, [0, 1, 50])
    texel, _, _ = atlas_mod.texel_points(atlas)
    assert len(texel) * texel_m**2 == pytest.approx(mesh.area, rel=0.10)


def test_texel_points_are_the_texel_centres(sphere_atlas):
    """Each covered texel's surface point maps back through the face's UVs to that texel's centre
    ((col + 0.5) / W, (row + 0.5) / H: glTF's convention) to round-off, and texel_of finds it."""
    _, atlas = sphere_atlas
    texel, face, bary = atlas_mod.texel_points(atlas)
    uv = atlas.uv_at(face, bary)
    assert np.allclose(uv[:, 0], (texel % atlas.width + 0.5) / atlas.width, atol=1e-9)
    assert np.allclose(uv[:, 1], (texel // atlas.width + 0.5) / atlas.height, atol=1e-9)
    assert np.array_equal(atlas.texel_of(face, bary), texel)


def test_lookup_is_exact_for_a_linear_map(sphere_atlas):
    """Bilinear lookup reproduces a map linear in (col, row) exactly at any point inside the texel
    centres' hull: value = 2 u W + 3 v H - 1 (u, v the point's UV)."""
    _, atlas = sphere_atlas
    rows, cols = np.mgrid[0 : atlas.height, 0 : atlas.width].astype(float)
    image = (2 * (cols + 0.5) + 3 * (rows + 0.5) - 1)[:, :, None]
    texel, face, bary = atlas_mod.texel_points(atlas)
    rng = np.random.default_rng(0)
    b = rng.dirichlet(np.ones(3), size=len(face))
    uv = atlas.uv_at(face, b)
    inside = (
        (uv[:, 0] * atlas.width > 0.5)
        & (uv[:, 0] * atlas.width < atlas.width - 0.5)
        & (uv[:, 1] * atlas.height > 0.5)
        & (uv[:, 1] * atlas.height < atlas.height - 0.5)
    )
    expected = 2 * uv[:, 0] * atlas.width + 3 * uv[:, 1] * atlas.height - 1
    assert np.allclose(atlas.lookup(image, face, b)[inside, 0], expected[inside], atol=1e-9)


def test_dilate_fills_rings_with_the_neighbours_mean():
    """One filled texel of value 5 in an empty 5 x 5 map: after one ring the 3 x 3 block around it is
    5, after two the whole map; filled texels never change."""
    image = np.zeros((5, 5, 1))
    image[2, 2] = 5.0
    filled = np.zeros((5, 5), bool)
    filled[2, 2] = True
    one = atlas_mod.dilate(image, filled, texels=1)
    assert np.allclose(one[1:4, 1:4], 5.0) and np.allclose(one[0], 0.0)
    assert np.allclose(atlas_mod.dilate(image, filled, texels=2), 5.0)


def test_at_vertices_of_a_constant_map():
    """A constant map read at the vertices is the constant (every corner's lookup agrees)."""
    mesh = trimesh.creation.box()
    atlas = unwrap(mesh.vertices, mesh.faces, texel_m=0.05)
    image = np.full((atlas.height, atlas.width, 3), [0.2, 0.4, 0.6])
    assert np.allclose(atlas.at_vertices(image, mesh.faces, len(mesh.vertices)), [0.2, 0.4, 0.6])


def test_a_crash_of_the_unwrapper_is_an_error_not_the_end_of_the_fit():
    """unwrap runs xatlas in a child process (pipeline.unwrap.in_child): xatlas 0.0.11 dies of a
    segmentation fault on an 81 920-face icosphere (and on users' large scans), which in-process would
    end the fit with nothing written.  A child that dies so is an UnwrapFailed naming the mesh's size;
    one that returns hands its result back, one that raises its exception."""
    vertices, faces = np.ones((5, 3), np.float32), np.array([[0, 1, 2]] * 5, np.uint32)
    np.testing.assert_array_equal(in_child(np.add, vertices, faces), vertices + faces)
    with pytest.raises(ValueError, match="broadcast"):  # an error in the child is raised here as itself
        in_child(np.add, vertices, faces[:2])
    with pytest.raises(UnwrapFailed, match="5 faces"):
        in_child(segfault, vertices, faces)
