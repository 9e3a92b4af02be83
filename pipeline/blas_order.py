"""Small float64 products summed in the order this machine's OpenBLAS sums them, for numba kernels.

A kernel that replaces NumPy's small products (``@`` of a few rows, ``J.T @ J``, ``x @ B``)
with scalar loops gives NumPy's results bit for bit only if it makes the same floating-point
operations in the same order. On the machines these were written for (OpenBLAS 0.3.31; Zen 4
here, AVX2/FMA), NumPy's small products go to OpenBLAS's dgemm, dsyrk, ddot and dgemv_n
kernels, which sum

* each entry of a matrix product (dgemm, dsyrk) and a short dot product (ddot) as one chain of
  fused multiply-adds from +0.0 in k order: ``acc = fma(a_q, b_q, acc)``
  (:func:`matmul`, :func:`matmul_at`, :func:`matmul_bt`, :func:`dot`);
* a vector-matrix product ``x @ B`` (dgemv_n on the column-major ``B^T x``) in blocks of 4, 2
  and 1 terms added to each output, the last ``n % 4`` outputs as one fused chain
  (:func:`vecmat`).

:func:`fma` is IEEE 754's fusedMultiplyAdd (LLVM ``llvm.fma.f64``), rounded once. On a CPU or
BLAS that sums otherwise, these give NumPy's results to rounding, not to the bit: the kernels'
tests probe which (tests/measure/test_measure_kernels.py, tests/triangulate/test_eccentricity_kernels.py).
Users: the eccentricity step (:mod:`crossfield.imaging.eccentricity`) and the measure stage
(``plugins/measure_plan.py``, through :mod:`crossfield.plugin_api`).
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils
from numba.core import types as nb_types
from numba.extending import intrinsic

__all__ = ["dot", "fma", "matmul", "matmul_at", "matmul_bt", "quadratic", "vecmat"]

_njit = numba.njit(cache=True, nogil=True, error_model="numpy")


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (IEEE 754 fusedMultiplyAdd; LLVM ``llvm.fma.f64``)."""
    sig = nb_types.float64(nb_types.float64, nb_types.float64, nb_types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64")
        return builder.call(fn, args)

    return sig, codegen


@_njit
def dot(x, y):
    """``x @ y`` of two (n,) vectors as OpenBLAS's ddot sums a short one: from +0.0,
    ``acc = fma(x_q, y_q, acc)`` for q = 0 .. n-1 (a sum of zeros is +0.0)."""
    acc = 0.0
    for q in range(x.shape[0]):
        acc = fma(x[q], y[q], acc)
    return acc


@_njit
def matmul(A, B):
    """``A @ B`` (m, k) x (k, n) as OpenBLAS's small dgemm / dsyrk kernels sum each entry:
    from +0.0, ``acc = fma(A[i, q], B[q, j], acc)`` for q = 0 .. k-1."""
    m, k = A.shape
    n = B.shape[1]
    C = np.empty((m, n))
    for i in range(m):
        for j in range(n):
            acc = 0.0
            for q in range(k):
                acc = fma(A[i, q], B[q, j], acc)
            C[i, j] = acc
    return C


@_njit
def matmul_bt(A, B):
    """``A @ B.T`` (m, k) x (n, k) -> (m, n), summed as :func:`matmul`."""
    m, k = A.shape
    n = B.shape[0]
    C = np.empty((m, n))
    for i in range(m):
        for j in range(n):
            acc = 0.0
            for q in range(k):
                acc = fma(A[i, q], B[j, q], acc)
            C[i, j] = acc
    return C


@_njit
def matmul_at(A, B):
    """``A.T @ B`` (k, m) x (k, n) -> (m, n), summed as :func:`matmul`."""
    k, m = A.shape
    n = B.shape[1]
    C = np.empty((m, n))
    for i in range(m):
        for j in range(n):
            acc = 0.0
            for q in range(k):
                acc = fma(A[q, i], B[q, j], acc)
            C[i, j] = acc
    return C


@_njit
def vecmat(x, B):
    """``x @ B``, x (k,), B (k, n) C-ordered, as OpenBLAS's dgemv_n sums it (the column-major
    ``B^T x``): outputs ``j < n & -4`` in the 4-row micro-kernels, the k terms in blocks of 4
    (``fma(x0 b0, x1 b1)``, then ``+ x2 b2``, ``+ x3 b3`` fused), of 2 (``fma(x0 b0, x1 b1)``)
    and of 1 (``x0 b0``), each block added to the output; the last ``n % 4`` outputs one
    fused chain as :func:`dot`. Checked for the shapes used here: (3, 3), (3, 6), (4, 4),
    (6, 6)."""
    k, n = B.shape
    y = np.empty(n)
    n_main = n & -4
    for j in range(n_main):
        acc = 0.0
        q = 0
        while q + 4 <= k:
            t = fma(x[q], B[q, j], x[q + 1] * B[q + 1, j])
            t = fma(x[q + 2], B[q + 2, j], t)
            t = fma(x[q + 3], B[q + 3, j], t)
            acc = acc + t
            q += 4
        if k - q >= 2:
            acc = acc + fma(x[q], B[q, j], x[q + 1] * B[q + 1, j])
            q += 2
        if k - q == 1:
            acc = acc + x[q] * B[q, j]
        y[j] = acc
    for j in range(n_main, n):
        acc = 0.0
        for q in range(k):
            acc = fma(x[q], B[q, j], acc)
        y[j] = acc
    return y


@_njit
def quadratic(g, C):
    """``g @ C @ g``: ``(g @ C) @ g``, as :func:`vecmat` and :func:`dot`."""
    return dot(vecmat(g, C), g)
