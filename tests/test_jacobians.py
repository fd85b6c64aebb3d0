"""Every analytic Jacobian of the estimator against central finite differences, at seeded
random configurations (mink's habit)."""
from __future__ import annotations

import numpy as np
import pytest

import dataclasses

from tapecell.estimator import _kernels, reference
from tapecell.estimator.chain import Chain
from tapecell.estimator.config import DEFAULT
from tapecell.estimator.strip import _strip_for, _tip_frame_rows
from tapecell.estimator.synthetic import make_capture, random_chain_angles
from tapecell.estimator.tape import TapeSpec

EPS = 1e-6


def _fd(fun, x: np.ndarray) -> np.ndarray:
    """Central differences of fun (R^P -> R^k, any shape) at x: (k..., P)."""
    cols = []
    for i in range(x.size):
        d = np.zeros_like(x)
        d.flat[i] = EPS
        cols.append((fun(x + d) - fun(x - d)) / (2 * EPS))
    return np.stack(cols, axis=-1)


def _spec(rng) -> TapeSpec:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return TapeSpec(np.full(5, 0.03), 0.03, rng.normal(scale=0.01, size=3), R)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("compiled", [True, False])
def test_chain_points_jacobian(seed, compiled):
    """Sample points and corners of the plate chain (compiled kernel and NumPy reference)."""
    rng = np.random.default_rng(seed)
    chain = Chain(_spec(rng), cfg=dataclasses.replace(DEFAULT, compiled=compiled))
    a = random_chain_angles(rng, 5)
    points = _kernels.points if compiled else reference.chain_points
    pts = lambda x: points(chain, x.reshape(1, 5, 3), False)[0][0]   # noqa: E731
    J = points(chain, a[None], True)[1][0]
    assert np.allclose(J, _fd(pts, a.ravel()), atol=1e-7)


@pytest.mark.parametrize("seed", range(3))
def test_chain_corners_jacobian(seed):
    rng = np.random.default_rng(10 + seed)
    chain = Chain(_spec(rng))
    a = random_chain_angles(rng, 5)
    c, J = chain.corners(a)
    assert np.allclose(J, _fd(lambda x: chain.corners(x.reshape(5, 3))[0], a.ravel()), atol=1e-7)


@pytest.mark.parametrize("seed", range(2))
def test_strip_corners_jacobian(seed):
    rng = np.random.default_rng(20 + seed)
    strip = _strip_for(_spec(rng), DEFAULT)
    x = rng.normal(scale=0.2, size=strip.T.shape[1])
    c, J = strip.corners(x)
    assert np.allclose(J, _fd(lambda y: strip.corners(y)[0], x), atol=1e-7)


def test_tip_frame_rows_jacobian():
    rng = np.random.default_rng(30)
    chain = Chain(_spec(rng))
    a = random_chain_angles(rng, 5)
    target = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rows = _tip_frame_rows(chain, target, 1.0)

    def r(x):
        c, J = chain.corners(x.reshape(5, 3))
        return rows(c, J)[0]

    c, J = chain.corners(a)
    assert np.allclose(rows(c, J)[1], _fd(r, a.ravel()), atol=1e-7)


def test_pixel_jacobian_pinhole():
    """d(u, v)/d(angles) of the pinhole projection (without distortion, as the fit uses it)."""
    capture = make_capture(40)
    camera = capture.views[0].camera
    rng = np.random.default_rng(40)
    chain = Chain(capture.tape)
    a = random_chain_angles(rng, 5)
    pts, J = chain.points(a[None], True)
    u, v, x, y, z = reference.project(camera, pts)
    Juv = reference.pixel_jacobian(camera, x, y, z, J)

    def uv(q):
        p, _ = chain.points(q.reshape(1, 5, 3), False)
        uu, vv, *_ = reference.project(camera, p)
        return np.stack([uu, vv], axis=-1)

    assert np.allclose(Juv[0], _fd(uv, a.ravel())[0], rtol=1e-5, atol=1e-4)
