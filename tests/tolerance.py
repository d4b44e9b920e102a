"""Tolerances for float results whose last bits are not defined: relative to the values compared.

XLA CPU (and BLAS) results change in their last bits with the thread count and the CPU (the
order of a reduction, the blocking of a matmul, FMA or not). An absolute tolerance such as
`atol=1e-6` is then right for elements of one magnitude and flips for others; these compare
with a relative tolerance and an absolute floor proportional to the largest value compared
(rounding noise is set by the computation's scale, not by an element that happens to be near 0).
Bit-exact comparisons of the same computation keep `assert_array_equal`.
"""

from __future__ import annotations

import numpy as np


def assert_close(actual, desired, *, rtol: float = 1e-5, floor: float = 1e-6, err_msg: str = "") -> None:
    """|actual - desired| <= rtol |desired| + floor * max|desired|, elementwise (shapes must agree)."""
    actual, desired = np.asarray(actual, np.float64), np.asarray(desired, np.float64)
    assert actual.shape == desired.shape, (actual.shape, desired.shape)
    scale = float(np.abs(desired).max()) if desired.size else 0.0
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=floor * scale, err_msg=err_msg)
