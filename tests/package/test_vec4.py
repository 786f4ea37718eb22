"""Four-lane vectors (:mod:`mpcrl_lite._util.vec4`): every operation gives, lane by lane, the
bits of the same operation on floats in numba, NaN, infinities, signed zeros and subnormals
included."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from mpcrl_lite._util.vec4 import LANES, vabs, vload, vmax, vmin, vsplat, vstore, where_gt, where_lt


@numba.njit(error_model="numpy")
def _vector_ops(a, b, out):
    for k in range(0, a.size, LANES):
        x, y = vload(a, k), vload(b, k)
        vstore(out, 0 * a.size + k, x + y)
        vstore(out, 1 * a.size + k, x - y)
        vstore(out, 2 * a.size + k, x * y)
        vstore(out, 3 * a.size + k, x / y)
        vstore(out, 4 * a.size + k, -x)
        vstore(out, 5 * a.size + k, vabs(x))
        vstore(out, 6 * a.size + k, vmax(x, y))
        vstore(out, 7 * a.size + k, vmin(x, y))
        vstore(out, 8 * a.size + k, where_gt(x, y, x, vsplat(7.0)))
        vstore(out, 9 * a.size + k, where_lt(x, y, vsplat(-7.0), y))
        vstore(out, 10 * a.size + k, 2.5 * x - y / 3.0 + 1)
        vstore(out, 11 * a.size + k, (x * y + 1.5) / (x - y) - 2.0 * x)


@numba.njit(error_model="numpy")
def _scalar_ops(a, b, out):
    for k in range(a.size):
        x, y = a[k], b[k]
        out[0 * a.size + k] = x + y
        out[1 * a.size + k] = x - y
        out[2 * a.size + k] = x * y
        out[3 * a.size + k] = x / y
        out[4 * a.size + k] = -x
        out[5 * a.size + k] = abs(x)
        out[6 * a.size + k] = max(x, y)
        out[7 * a.size + k] = min(x, y)
        out[8 * a.size + k] = x if x > y else 7.0
        out[9 * a.size + k] = -7.0 if x < y else y
        out[10 * a.size + k] = 2.5 * x - y / 3.0 + 1
        out[11 * a.size + k] = (x * y + 1.5) / (x - y) - 2.0 * x


def _awkward_values(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 1.0, size) * 10.0 ** rng.integers(-300, 300, size)
    special = [np.nan, np.inf, -np.inf, 0.0, -0.0, 5e-324, -5e-324, 1.0, -1.0, 1e308]
    a[rng.choice(size, 40, replace=False)] = rng.choice(special, 40)
    return a


@pytest.mark.parametrize("seed", [0, 1])
def test_each_operation_gives_the_scalar_bits(seed):
    size = 4000
    a, b = _awkward_values(size, seed), _awkward_values(size, seed + 10)
    b[:12] = a[:12]  # ties
    vec, ref = np.empty(12 * size), np.empty(12 * size)
    _vector_ops(a, b, vec)
    _scalar_ops(a, b, ref)
    # the same bit patterns (NaN payloads aside: compare NaN positions, then the rest by bits)
    assert np.array_equal(np.isnan(vec), np.isnan(ref))
    finite = ~np.isnan(ref)
    assert np.array_equal(vec[finite].view(np.int64), ref[finite].view(np.int64))


def test_max_and_min_follow_numbas_order_with_nan():
    """``max(acc, v)`` keeps ``acc`` unless ``v > acc``: a NaN accumulator stays, a NaN value
    is passed over (and likewise ``min``)."""
    acc = np.array([np.nan, 1.0, np.nan, -0.0])
    v = np.array([2.0, np.nan, np.nan, 0.0])
    out = np.empty(8)

    @numba.njit(error_model="numpy")
    def run(acc, v, out):
        vstore(out, 0, vmax(vload(acc, 0), vload(v, 0)))
        vstore(out, 4, vmin(vload(acc, 0), vload(v, 0)))

    run(acc, v, out)
    assert np.isnan(out[0]) and out[1] == 1.0 and np.isnan(out[2])
    assert out[3] == 0.0 and np.signbit(out[3])  # -0.0 kept: 0.0 > -0.0 is false
    assert np.isnan(out[4]) and out[5] == 1.0


def test_loads_and_stores_use_flat_offsets_of_any_array():
    a = np.arange(24.0).reshape(2, 3, 4)
    out = np.zeros((3, 4))

    @numba.njit(error_model="numpy")
    def run(a, out):
        vstore(out, 4, vload(a, 12) + vload(a, 16))

    run(a, out)
    np.testing.assert_array_equal(out[1], a[1, 0] + a[1, 1])
    assert not out[0].any() and not out[2].any()
