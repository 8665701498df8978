"""Comparing float64 results that come out of numpy/scipy routines, whose last bits may differ
between machines (SIMD width, BLAS, libm, scipy's expm): equal up to the rounding that the
computation itself may accumulate, never bit for bit.

The bound: every float64 operation rounds its result to within eps/2 relative (eps = 2**-52 =
2.2e-16); a chain of ``operations`` sequential operations of a stable computation carries at
most about ``operations`` such errors, each relative to the largest magnitude involved. So two
machines may differ by up to ``operations * eps * max|expected|``, and anything larger is a
different computation, not rounding.
"""

from __future__ import annotations

import numpy as np

EPS = float(np.finfo(np.float64).eps)


def rounding_tolerance(expected: np.ndarray, operations: int) -> float:
    """The largest difference that ``operations`` sequential float64 roundings can explain."""
    return operations * EPS * float(np.max(np.abs(expected)))


def assert_equal_up_to_rounding(actual: np.ndarray, expected: np.ndarray, operations: int, err_msg: str = "") -> None:
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape and actual.dtype == expected.dtype, (err_msg, actual.shape, expected.shape)
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rounding_tolerance(expected, operations), err_msg=err_msg)
