"""pipeline.core.procedural_envmaps against closed forms: the white furnace's power, a sun disk's power and
direction at any map height, the CIE overcast sky's integral, and the spec grammar's errors."""

import numpy as np
import pytest

from pipeline.core.envmap import equirect_directions, equirect_solid_angles
from pipeline.core.procedural_envmaps import direction_from_angles, envmap_from_spec, make_envmap, parse_env_spec


def power(env: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """sum L dω over the map (or over ``mask``), RGB."""
    omega = np.broadcast_to(equirect_solid_angles(env.shape[0])[:, None], env.shape[:2])
    m = np.ones(env.shape[:2], bool) if mask is None else mask
    return (env[m] * omega[m][:, None]).sum(axis=0)


def test_constant_map_holds_4_pi_times_its_radiance():
    """A constant map of radiance 2 holds 8 pi of power (4 pi sr x 2) under the equirect solid angles."""
    np.testing.assert_allclose(power(make_envmap("constant", 32, value=2.0)), 8 * np.pi, rtol=1e-6)


@pytest.mark.parametrize("height", [16, 64, 256])
def test_sun_disk_has_the_irradiance_asked_for_and_points_where_asked(height):
    """sun+sky with no sky: all the power is the sun's (30, times its warm colour), centred on
    (elev, az) to within a pixel, at any map height (the disk is smaller than a pixel at 16 rows)."""
    env = make_envmap("sun+sky", height, elev=35.0, az=120.0, sun=30.0, sky=0.0)
    dirs = equirect_directions(height)
    lum = env.mean(axis=2)
    sun = lum > 0.5 * lum.max()
    np.testing.assert_allclose(power(env, sun), 30.0 * np.array([1.0, 0.95, 0.85]), rtol=1e-6)
    weight = lum[sun] * np.broadcast_to(equirect_solid_angles(height)[:, None], lum.shape)[sun]
    centre = (dirs[sun] * weight[:, None]).sum(axis=0)
    centre /= np.linalg.norm(centre)
    pixel_deg = 180.0 / height
    assert np.degrees(np.arccos(centre @ direction_from_angles(35.0, 120.0))) < pixel_deg


def test_overcast_sky_integrates_to_its_closed_form():
    """CIE overcast L = Lz (1 + 2 cos θ) / 3 over the upper hemisphere: (2π + 2π) Lz / 3 = 4π Lz / 3,
    times the sky's tint (0.95, 0.97, 1)."""
    env = make_envmap("overcast", 256, zenith=1.0, ground=0.0)
    upper = equirect_directions(256)[..., 2] > 0
    np.testing.assert_allclose(power(env, upper), 4 * np.pi / 3 * np.array([0.95, 0.97, 1.0]), rtol=1e-3)


def test_spec_grammar():
    """An environment spec 'name:key=value,...' parses to its name, height and parameters, and each kind of bad
    spec (unknown name, missing '=', a non-number, an unknown key, height < 2) is refused with a message
    naming the fault."""
    assert parse_env_spec("area:n=3,seed=2,height=32") == ("area", 32, {"n": 3.0, "seed": 2.0})
    assert envmap_from_spec("smooth:height=8").shape == (8, 16, 3)
    for spec, words in (
        ("sunny", "unknown environment"),
        ("area:n", "key=value"),
        ("area:n=x", "must be a number"),
        ("area:nope=1", "no parameter 'nope'"),
        ("area:height=1", "height must be >= 2"),
    ):
        with pytest.raises(ValueError, match=words):
            parse_env_spec(spec)
