"""Finite-difference checks of GTSAM factors' Jacobians (shared by the IMU factor tests)."""

import numpy as np


def assert_jacobians_match_central_differences(factor, values, keys, dims, eps: float = 1e-6,
                                               rel_tol: float = 2e-4) -> None:
    """Each column of ``factor``'s whitened Jacobian at ``values`` (blocks of ``dims`` tangent
    dimensions, in the order of ``keys``) equals the central difference of its whitened error along
    that tangent direction (``values.retract``), to ``rel_tol`` of the column's largest entry (at
    least of 1); the linearisation's right-hand side is minus the whitened error."""
    import gtsam

    A, b = factor.linearize(values).jacobian()
    A = np.asarray(A)
    np.testing.assert_allclose(-np.asarray(b), factor.whitenedError(values), atol=1e-9)
    col = 0
    for key, d in zip(keys, dims):
        for k in range(d):
            delta = gtsam.VectorValues()
            for kk, dd in zip(keys, dims):
                v = np.zeros(dd)
                if kk == key:
                    v[k] = eps
                delta.insert(kk, v)
            plus = factor.whitenedError(values.retract(delta))
            minus = factor.whitenedError(values.retract(delta.scale(-1.0)))
            np.testing.assert_allclose(A[:, col], (plus - minus) / (2 * eps),
                                       atol=rel_tol * max(1.0, np.abs(A[:, col]).max()))
            col += 1
