"""pipeline.core.lighting_scale: the closed-form error of a candidate at every factor of a known
lighting, and what the profile of those errors says of the factor."""

import numpy as np

from pipeline.core.candidate import Observations
from pipeline.core.lighting_scale import SCALES, ScaleProfile, level_errors
from pipeline.core.material_fit import TRIM_FRACTION, trimmed_rmse


def test_level_errors_match_the_direct_evaluation(rng):
    """At any scale s the vectorized error equals the fit's own steps written out: rho the weighted least
    squares of radiance / s - specular on the diffuse, clipped to [0, 1] per channel, then
    material_fit.trimmed_rmse of radiance - s (rho Q + R) — to 1e-12 relative."""
    n = 500
    shade, specular = rng.uniform(0.1, 1.0, (n, 3)), rng.uniform(0.0, 0.3, (n, 3))
    truth = 1.7 * (np.array([0.6, 0.3, 0.9]) * shade + specular)
    obs = Observations(truth + rng.normal(0, 0.01, (n, 3)), rng.uniform(0.5, 1.5, n), np.zeros(n, np.int64))
    scales = np.array([0.3, 1.0, 1.7, 4.0])
    got = level_errors(shade, specular, obs, scales)
    for s, e in zip(scales, got):
        w = obs.weight[:, None]
        rho = np.clip((w * shade * (obs.radiance / s - specular)).sum(0) / (w * shade * shade).sum(0), 0, 1)
        want = trimmed_rmse(obs.radiance - s * (rho * shade + specular), obs.weight, TRIM_FRACTION)
        assert abs(e / want - 1) < 1e-12, (s, e, want)
    assert np.argmin(level_errors(shade, specular, obs)) == np.argmin(np.abs(np.log(SCALES / 1.7)))


def test_profile_readings():
    """A V-shaped profile reads "about" its least, between the grid's scales (a parabola's vertex: 1.7
    to 0.1 %), and accepts a run around it; one flat above a bound (a Lambertian: any albedo <= 1
    fits) reads "at least" that bound and accepts no upper end; the map as given is taken where its
    error is within the limit, else the factor to apply is the reading."""
    v = ScaleProfile.of(np.abs(np.log(SCALES / 1.7)) + 0.01, tolerance=0.05, noise=0.05)
    kind, factor = v.reading()
    assert kind == "about" and abs(factor / 1.7 - 1) < 1e-3, factor
    assert v.accepted[0] < 1.7 < v.accepted[1] and not v.accepts_one and v.factor() == factor
    flat = ScaleProfile.of(np.where(SCALES < 0.6, 0.6 - SCALES, 0.0) + 0.001, tolerance=0.05, noise=0.0)
    kind, bound = flat.reading()
    assert kind == "at least" and abs(bound / 0.6 - 1) < 0.03 and flat.accepted[1] is None
    assert flat.accepts_one and flat.factor() == 1.0
