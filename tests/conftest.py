"""Shared fixtures: a seeded random generator (every test is reproducible).

The test process runs BLAS on one thread, as the fit stage (``--blas-threads 1``) and relight's
renderer already do: on a 2-core machine shared with other jobs, multithreaded OpenBLAS's threads
fight them, and the tests' own small products ran 5-70x slower than on one thread (test_planar's:
0.1 s alone, 2-7 s after earlier tests had started the BLAS threads; docs/ci.md, Inner loop).  OpenCV's
own bundled OpenBLAS and the processes a test starts are not affected.
"""

import numpy as np
import pytest
import scipy.linalg  # noqa: F401  (loads SciPy's own OpenBLAS, so that the limit below covers it too)
from threadpoolctl import threadpool_limits

threadpool_limits(limits=1, user_api="blas")


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
