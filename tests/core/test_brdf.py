"""BRDF formulas against closed forms and quadrature over the hemisphere."""

import numpy as np
import pytest

from pipeline.core.brdf import Brdf, beckmann_distribution, cosine_weighted_brdf, reflect


def _hemisphere_rule(n_theta=400, n_phi=800):
    """Midpoint rule in (cos theta, phi) on the upper hemisphere: exact weights 2 pi / (n_theta n_phi)."""
    mu = (np.arange(n_theta) + 0.5) / n_theta
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    m, p = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - m**2)
    dirs = np.stack([s * np.cos(p), s * np.sin(p), m], -1).reshape(-1, 3)
    return dirs, np.full(len(dirs), 2 * np.pi / (n_theta * n_phi))


def test_lambert_directional_albedo_equals_albedo():
    """A Lambertian BRDF's cosine-weighted integral over the hemisphere (its directional albedo) is its albedo,
    per channel, to the grid's 1e-5."""
    dirs, w = _hemisphere_rule()
    n = np.tile([0.0, 0.0, 1.0], (len(dirs), 1))
    wo = np.tile([0.3, 0.0, np.sqrt(1 - 0.09)], (len(dirs), 1))
    brdf = Brdf("lambert", albedo=[0.2, 0.5, 1.0])
    got = (cosine_weighted_brdf(brdf, n, dirs, wo) * w[:, None]).sum(0)
    # midpoint rule on a linear integrand in cos(theta): error ~1e-6 from the grid
    np.testing.assert_allclose(got, [0.2, 0.5, 1.0], rtol=1e-5)


def test_beckmann_is_normalized():
    """The Beckmann distribution integrates to 1 against cos(theta_h) over the hemisphere for sigma 0.1-0.6
    (within the 2000-node grid's 2e-3)."""
    dirs, w = _hemisphere_rule(2000, 16)  # D depends on theta only
    for sigma in (0.1, 0.3, 0.6):
        total = (beckmann_distribution(dirs[:, 2], sigma) * dirs[:, 2] * w).sum()
        assert total == pytest.approx(1.0, rel=2e-3)  # sharp lobe on a 2000-node grid: ~1e-3


@pytest.mark.parametrize("view_cos", [1.0, 0.7, 0.3])
def test_phong_transfer_has_at_most_unit_energy(view_cos):
    """The R&H Phong transfer (s = 50, unit specular weight) reflects exactly 1 at normal view and never more than 1 at
    oblique views, where the horizon clips it."""
    dirs, w = _hemisphere_rule()
    n = np.tile([0.0, 0.0, 1.0], (len(dirs), 1))
    wo = np.tile([np.sqrt(1 - view_cos**2), 0.0, view_cos], (len(dirs), 1))
    brdf = Brdf("phong", albedo=[0, 0, 0], specular_weight=[1, 1, 1], exponent=50.0)
    total = (cosine_weighted_brdf(brdf, n, dirs, wo)[:, 0] * w).sum()
    # the lobe integrates to 1 over the sphere; the horizon clips it at grazing views only
    assert total <= 1.0 + 1e-3
    if view_cos == 1.0:
        assert total == pytest.approx(1.0, rel=1e-3)


@pytest.mark.parametrize("beckmann_sigma", [0.1, 0.3])
@pytest.mark.parametrize("view_cos", [1.0, 0.5, 0.15])
def test_microfacet_never_returns_more_than_it_receives(beckmann_sigma, view_cos):
    """The Torrance-Sparrow lobe with F = 1 keeps more than half the energy and never creates any (<= 1 + 2e-3),
    for Beckmann sigma 0.1 and 0.3 at normal to grazing views."""
    dirs, w = _hemisphere_rule(1000, 1000)
    n = np.tile([0.0, 0.0, 1.0], (len(dirs), 1))
    wo = np.tile([np.sqrt(1 - view_cos**2), 0.0, view_cos], (len(dirs), 1))
    brdf = Brdf("microfacet", albedo=[0, 0, 0], f0=[1, 1, 1], beckmann_sigma=beckmann_sigma)
    total = (cosine_weighted_brdf(brdf, n, dirs, wo)[:, 0] * w).sum()
    assert 0.5 < total <= 1.0 + 2e-3  # F = 1: the lobe keeps most energy, never creates any


def test_reflect_is_the_mirror_direction():
    """r = 2 (n.w) n - w: the same angle to n on the other side, in the plane of n and w — the
    normal itself comes back, a tangent direction flips, and reflecting twice is the identity
    (the identity alone would pass that last check, not the first two)."""
    rng = np.random.default_rng(0)
    n = rng.normal(size=(10, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    w = rng.normal(size=(10, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    r = reflect(w, n)
    np.testing.assert_allclose(np.sum(r * n, axis=1), np.sum(w * n, axis=1), atol=1e-12)  # same angle to n
    np.testing.assert_allclose(r + w, 2 * np.sum(w * n, axis=1, keepdims=True) * n, atol=1e-12)  # in-plane mirror
    np.testing.assert_allclose(reflect(n, n), n, atol=1e-12)
    tangent = np.cross(n, w)
    np.testing.assert_allclose(reflect(tangent, n), -tangent, atol=1e-12)
    np.testing.assert_allclose(reflect(r, n), w, atol=1e-12)


def test_brdf_type_holds_each_model_to_its_parameters():
    """The one parameter table: RGB parameters as 3 floats (a scalar is grey), principled's
    optional ones defaulted, a parameter of another model or a missing one refused, and the
    brdf.json form round-trips with JSON types."""
    glossy = Brdf("microfacet", albedo=[0.2, 0.3, 0.5], f0=0.04, beckmann_sigma=np.float32(0.2))
    assert glossy.f0 == (0.04, 0.04, 0.04) and type(glossy.beckmann_sigma) is float and glossy.roughness is None
    assert glossy.has_lobe and glossy.lobe_width == pytest.approx(0.2) and glossy.lobe_color.tolist() == [0.04] * 3
    assert glossy.with_lobe_color(0.5).f0 == (0.5, 0.5, 0.5)
    assert Brdf.from_lobe("phong", 0.2, 0.3, 40.0) == Brdf("phong", albedo=0.2, specular_weight=0.3, exponent=40.0)
    assert Brdf.from_dict({**glossy.to_dict(), "notes": "ignored"}) == glossy
    assert glossy.to_dict()["albedo"] == [0.2, 0.3, 0.5]
    plastic = Brdf("principled", base_color=(0.7, 0.45, 0.1), roughness=0.3)
    assert (plastic.metallic, plastic.ior, plastic.specular_tint) == (0.0, 1.5, (1.0, 1.0, 1.0))
    assert not plastic.has_lobe and plastic.albedo is None
    assert plastic.with_diffuse_color([0.1, 0.2, 0.3]).diffuse_color.tolist() == [0.1, 0.2, 0.3]
    assert Brdf("lambert", albedo=0.5).with_diffuse_color([0.1, 0.2, 0.3]).albedo == (0.1, 0.2, 0.3)
    with pytest.raises(ValueError, match="no parameter 'roughness'"):
        Brdf("lambert", albedo=0.5, roughness=0.3)
    with pytest.raises(ValueError, match="no parameter 'roughness'"):
        Brdf("microfacet", albedo=0.5, f0=0.04, beckmann_sigma=0.2, roughness=0.2)
    with pytest.raises(ValueError, match="needs 'exponent'"):
        Brdf("phong", albedo=0.5, specular_weight=0.1)
    with pytest.raises(ValueError, match="unknown BRDF model"):
        Brdf("velvet", albedo=0.5)
