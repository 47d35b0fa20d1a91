"""fgslam.core.arrays: the per-pixel reductions give the same bits as numpy's own, non-finite values and
signed zeros included."""

import numpy as np
import pytest

from fgslam.core.arrays import finite_rows, min_rows, norm2_rows


def _awkward(shape, dtype, seed):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(shape) * rng.choice([1e-30, 1.0, 1e30], shape)
    x[rng.random(shape) < 0.05] = np.nan
    x[rng.random(shape) < 0.02] = np.inf
    x[rng.random(shape) < 0.02] = -np.inf
    x[rng.random(shape) < 0.03] = -0.0
    x[rng.random(shape) < 0.03] = 0.0
    return x.astype(dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("components", [2, 3])
def test_finite_and_min_rows_equal_numpy(dtype, components):
    x = _awkward((60, 80, components), dtype, components)
    assert np.array_equal(finite_rows(x), np.isfinite(x).all(-1))
    got, want = min_rows(x), x.min(-1)
    assert got.dtype == want.dtype
    assert np.array_equal(got, want, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(want))
    assert not np.shares_memory(got, x)  # a new array, as numpy's


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_norm2_rows_equals_numpy(dtype):
    x = _awkward((60, 80, 2), dtype, 7)
    with np.errstate(over="ignore"):
        got, want = norm2_rows(x), np.linalg.norm(x, axis=-1)
    assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
    with pytest.raises(ValueError, match="length 2"):
        norm2_rows(np.zeros((4, 3)))
