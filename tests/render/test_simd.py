"""The SIMD vectors of the compiled CPU renderer (`render/cpu/simd.py`) against NumPy, lane by lane."""

from fractions import Fraction

import numba
import numpy as np
import pytest
from numba import njit

from surfsplat.render.cpu import kernels
from surfsplat.render.cpu.simd import (
    LANES,
    any_lane,
    count,
    fma,
    half_iota,
    lane,
    lane_sums,
    load,
    load_at,
    select,
    splat,
    store,
    store_at,
    upper_lanes,
)

FLOATS = (np.float32, np.float64)


@njit
def _arithmetic(x, out):
    ft = x.dtype.type
    a, b = load(x, 0, 0), load(x, 1, 0)
    store(out, 0, 0, a + b)
    store(out, 1, 0, a - ft(0.25))
    store(out, 2, 0, ft(3.0) * b)
    store(out, 3, 0, a / b)
    store(out, 4, 0, -a)
    store(out, 5, 0, min(a, b))
    store(out, 6, 0, max(a, ft(0.5)))
    store(out, 7, 0, select((a < b) & ~(a < ft(0.1)), a, b))
    store(out, 8, 0, select((a >= b) | (b == ft(0.5)) | (a != a), splat(ft(1.0)), splat(ft(0.0))))
    store(out, 9, 0, half_iota(ft) + select(upper_lanes(), splat(ft(100.0)), splat(ft(0.0))))


@pytest.mark.parametrize("dtype", FLOATS)
def test_lanes_compute_what_numpy_computes(dtype):
    rng = np.random.default_rng(0)
    x = rng.uniform(0.05, 1.0, (2, LANES)).astype(dtype)
    x[1, 3] = 0.5
    out = np.zeros((10, LANES), dtype)
    _arithmetic(x, out)
    a, b = x
    expected = [
        a + b,
        a - dtype(0.25),
        dtype(3.0) * b,
        a / b,
        -a,
        np.minimum(a, b),
        np.maximum(a, 0.5),
        np.where((a < b) & ~(a < 0.1), a, b),
        ((a >= b) | (b == 0.5)).astype(dtype),
        np.arange(LANES) % (LANES // 2) + 100.0 * (np.arange(LANES) >= LANES // 2),
    ]
    for k, e in enumerate(expected):
        np.testing.assert_array_equal(out[k], np.asarray(e, dtype), err_msg=f"row {k}")
    assert out.dtype == dtype


@njit
def _fused(x, out):
    store(out, 0, 0, fma(load(x, 0, 0), load(x, 1, 0), load(x, 2, 0)))
    store(out, 1, 0, load(x, 0, 0) * load(x, 1, 0) + load(x, 2, 0))
    return fma(x[0, 0], x[1, 0], x[2, 0])


@pytest.mark.parametrize("dtype", FLOATS)
def test_fma_rounds_once(dtype):
    # (1 + e)^2 - (1 + 2e) = e^2 exactly; apart, the product rounds e^2 away.
    e = dtype(2.0 ** -(12 if dtype == np.float32 else 27))
    x = np.empty((3, LANES), dtype)
    x[0], x[1], x[2] = 1 + e, 1 + e, -(1 + 2 * e)
    out = np.empty((2, LANES), dtype)
    scalar = _fused(x, out)
    assert np.all(out[0] == e * e) and np.all(out[1] == 0.0)
    assert scalar == e * e
    # Random operands: the exactly rounded a * b + c (float64 checked against exact fractions).
    rng = np.random.default_rng(1)
    x = rng.standard_normal((3, LANES)).astype(dtype)
    _fused(x, out)
    if dtype == np.float64:
        exact = [float(Fraction(a) * Fraction(b) + Fraction(c)) for a, b, c in x.T]
        np.testing.assert_array_equal(out[0], exact)
    else:  # float32 operands: the product is exact in float64
        np.testing.assert_allclose(out[0], x[0].astype(np.float64) * x[1] + x[2], rtol=6e-8, atol=1e-30)


@njit
def _masks(x):
    m = load(x, 0, 0) > x.dtype.type(0.5)
    return any_lane(m), count(m), lane(load(x, 0, 0), 5)


def test_mask_reductions_and_lane():
    x = np.zeros((1, LANES))
    assert _masks(x) == (False, 0, 0.0)
    x[0, [2, 5, 15]] = 1.0
    assert _masks(x) == (True, 3, 1.0)


@njit
def _sums(x, out):
    store(out, 0, 0, lane_sums((load(x, 0, 0), load(x, 1, 0), load(x, 2, 0), load(x, 3, 0), load(x, 4, 0))))


@pytest.mark.parametrize("dtype", FLOATS)
def test_lane_sums_add_each_vector_in_a_fixed_tree(dtype):
    rng = np.random.default_rng(2)
    x = rng.standard_normal((5, LANES)).astype(dtype)
    out = np.full((1, LANES), np.nan, dtype)
    _sums(x, out)
    # Lane j takes lane j + 8, then j + 4, j + 2, j + 1: the same tree, in NumPy.
    tree = x.copy()
    width = LANES // 2
    while width >= 1:
        tree = tree[:, :width] + tree[:, width : 2 * width]
        width //= 2
    np.testing.assert_array_equal(out[0, :5], tree[:, 0])
    np.testing.assert_array_equal(out[0, 5:], 0.0)
    np.testing.assert_allclose(out[0, :5], x.astype(np.float64).sum(1), rtol=1e-5)


@njit
def _places(state, last):
    # Rows 1 and 2 at column 3 (two half rows), scaled; the int32 runs alike; row 3 whole, at
    # column LANES.
    v = load_at(state, (1, 3, 2, 3), 0)
    store_at(state, (1, 3, 2, 3), 0, v * state.dtype.type(2.0))
    store_at(last, (0, 8, 3, 0), 0, load_at(last, (0, 0, 3, 8), 0))
    store_at(state, (3,), LANES, load_at(state, (3,), LANES) + state.dtype.type(1.0))


def test_places_load_and_store_in_place():
    state = np.arange(4 * 2 * LANES, dtype=np.float32).reshape(4, 2 * LANES)
    last = np.arange(4 * LANES, dtype=np.int32).reshape(4, LANES)
    expected, expected_last = state.copy(), last.copy()
    half = LANES // 2
    expected[1, 3 : 3 + half] *= 2
    expected[2, 3 : 3 + half] *= 2
    expected[3, LANES:] += 1
    expected_last[0, 8:16], expected_last[3, 0:8] = last[0, 0:8], last[3, 8:16]
    _places(state, last)
    np.testing.assert_array_equal(state, expected)
    np.testing.assert_array_equal(last, expected_last)


@njit
def _whole_row(state):
    store_at(state, (0,), 0, load_at(state, (0,), 0) * state.dtype.type(2.0))


def test_a_whole_row_is_one_load_and_one_store():
    # The compositing's unpacked steps rely on it: two half-width accesses cost a shuffle each.
    state = np.ones((1, LANES), np.float32)
    _whole_row(state)
    np.testing.assert_array_equal(state, 2.0)
    ir = _whole_row.inspect_llvm(_whole_row.signatures[0])
    body = "".join(f for f in ir.split("\ndefine ")[1:] if "cpython" not in f.split("(")[0])
    assert body.count(f"load <{LANES} x float>") == 1
    assert body.count(f"store <{LANES} x float>") == 1
    assert "shufflevector" not in body


def test_a_place_must_be_one_or_four_integers():
    @njit
    def three(x):
        return load_at(x, (0, 0, 0), 0)

    with pytest.raises(numba.core.errors.TypingError):
        three(np.ones((1, LANES), np.float32))


@njit
def _exp_lanes(x, out):
    store(out, 0, 0, kernels._exp_nonpositive(load(x, 0, 0), x.dtype.type))


@pytest.mark.parametrize("dtype", FLOATS)
def test_vector_exponential_is_the_scalar_one_bit_for_bit(dtype):
    # The compositing evaluates alpha in lanes; the scalar path must give the very same bits.
    x = np.linspace(kernels.LOG_ALPHA_MIN - 3.0, 0.0, LANES).astype(dtype)[None]
    out = np.empty_like(x)
    _exp_lanes(x, out)
    scalar = np.array([kernels._exp_nonpositive(v, dtype) for v in x[0]], dtype)
    np.testing.assert_array_equal(out[0], scalar)


def test_float32_lanes_stay_float32():
    x = np.ones((2, LANES), np.float32)
    _arithmetic(x, np.zeros((10, LANES), np.float32))
    ir = _arithmetic.inspect_llvm(_arithmetic.signatures[0])
    body = "".join(f for f in ir.split("\ndefine ")[1:] if "cpython" not in f.split("(")[0])
    assert f"<{LANES} x float>" in body
    assert "double" not in body.replace("double*", "")


def test_mismatched_operands_do_not_compile():
    @njit
    def mixed(x, y):
        return load(x, 0, 0) + load(y, 0, 0)

    with pytest.raises(numba.core.errors.TypingError):
        mixed(np.ones((1, LANES), np.float32), np.ones((1, LANES), np.float64))
