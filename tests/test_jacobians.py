"""Every analytic Jacobian of the estimator against central finite differences, at seeded
random configurations (mink's habit)."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell.estimator import fit
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
def test_chain_points_jacobian(seed, compiled, monkeypatch):
    """Sample points and corners of the plate chain (compiled kernel and NumPy reference)."""
    monkeypatch.setattr(fit, "COMPILED", compiled)
    rng = np.random.default_rng(seed)
    chain = fit._Chain(_spec(rng))
    a = random_chain_angles(rng, 5)
    pts = (lambda x: fit._kernels.points(chain, x.reshape(1, 5, 3), False)[0][0]) if compiled else \
        (lambda x: chain.points(x.reshape(1, 5, 3), False)[0][0])
    J = (fit._kernels.points(chain, a[None], True) if compiled else chain.points(a[None], True))[1][0]
    assert np.allclose(J, _fd(pts, a.ravel()), atol=1e-7)


@pytest.mark.parametrize("seed", range(3))
def test_chain_corners_jacobian(seed):
    rng = np.random.default_rng(10 + seed)
    chain = fit._Chain(_spec(rng))
    a = random_chain_angles(rng, 5)
    c, J = chain.corners(a)
    assert np.allclose(J, _fd(lambda x: chain.corners(x.reshape(5, 3))[0], a.ravel()), atol=1e-7)


@pytest.mark.parametrize("seed", range(2))
def test_strip_corners_jacobian(seed):
    rng = np.random.default_rng(20 + seed)
    strip = fit._strip_for(_spec(rng))
    x = rng.normal(scale=0.2, size=strip.T.shape[1])
    c, J = strip.corners(x)
    assert np.allclose(J, _fd(lambda y: strip.corners(y)[0], x), atol=1e-7)


def test_tip_frame_rows_jacobian():
    rng = np.random.default_rng(30)
    chain = fit._Chain(_spec(rng))
    a = random_chain_angles(rng, 5)
    target = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rows = fit._tip_frame_rows(chain, target, 1.0)

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
    chain = fit._Chain(capture.tape)
    a = random_chain_angles(rng, 5)
    pts, J = chain.points(a[None], True)
    u, v, x, y, z = fit._project(camera, pts)
    Juv = fit._pixel_jacobian(camera, x, y, z, J)

    def uv(q):
        p, _ = chain.points(q.reshape(1, 5, 3), False)
        uu, vv, *_ = fit._project(camera, p)
        return np.stack([uu, vv], axis=-1)

    assert np.allclose(Juv[0], _fd(uv, a.ravel())[0], rtol=1e-5, atol=1e-4)
