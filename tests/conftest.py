"""Shared fixtures: a seeded random generator (every test is reproducible)."""

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20011)


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory):
    """Factory of small synthetic captures (pipeline.synth.make_test_capture), cached per session.

    ``tiny_capture(mesh="sphere", brdf="lambert:albedo=0.6", env="area", views=6, size=(96, 96),
    fmt="exr", **more)`` returns the capture folder (images/, mesh.ply, poses.json, capture.toml,
    gt/); the same arguments return the same folder.  Treat it as read-only.
    """
    from pipeline.synth import make_test_capture

    cache: dict = {}

    def make(**kwargs):
        key = repr(sorted(kwargs.items()))
        if key not in cache:
            cache[key] = make_test_capture(tmp_path_factory.mktemp("capture"), **kwargs)
        return cache[key]

    return make
