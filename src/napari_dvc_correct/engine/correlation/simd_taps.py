"""The tricubic B-spline tap sum written as 4-lane vector code (the innermost operation of IC-GN).

numba leaves LLVM's SLP vectorizer off, so the 64-tap sum of :func:`.interpolation.sample_interior`
compiles to 64 scalar multiply-adds and 64 scalar loads. Here the four x taps of a (z, y) row,
which are contiguous in a C-ordered volume, are one ``<4 x float>`` load; the sum is

``f = Σ_x wx · Σ_z wz · Σ_y wy · c[z, y, x-lanes]``

(16 vector loads and 20 vector multiply-adds), and each axis's four weights are one vector
polynomial ``A + t (B + t (C + t D))`` in the fractional position ``t``. Everything is float32, as
in the scalar path; the two differ by float32 rounding (a few units in the last place).

The vector code is emitted by a numba ``@intrinsic`` (llvmlite IR): LLVM lowers ``<4 x float>``
to SSE/AVX on x86 and NEON on ARM, so the kernel stays portable and cacheable.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from .._numba_setup import KERNEL_OPTIONS

_F32 = ir.FloatType()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_V4 = ir.VectorType(_F32, 4)

#: Cubic B-spline weights of the taps ``floor - 1 .. floor + 2`` as ``A + t (B + t (C + t D))``
#: (lane = tap; the same polynomials as :func:`.interpolation.bspline_weights`).
_A = (1 / 6, 4 / 6, 1 / 6, 0.0)
_B = (-3 / 6, 0.0, 3 / 6, 0.0)
_C = (3 / 6, -6 / 6, 3 / 6, 0.0)
_D = (-1 / 6, 3 / 6, -3 / 6, 1 / 6)


def _const4(values):
    return ir.Constant(_V4, [ir.Constant(_F32, float(np.float32(v))) for v in values])


def _splat(builder, vector, lane):
    mask = ir.Constant(ir.VectorType(_I32, 4), [lane] * 4)
    return builder.shuffle_vector(vector, ir.Constant(_V4, ir.Undefined), mask)


def _fma(builder, a, b, c):
    fn = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(_V4, [_V4, _V4, _V4]), "llvm.fma.v4f32"
    )
    return builder.call(fn, [a, b, c])


def _weights4(builder, t):
    vector = builder.insert_element(ir.Constant(_V4, ir.Undefined), t, ir.Constant(_I32, 0))
    vector = _splat(builder, vector, 0)
    w = _fma(builder, vector, _const4(_D), _const4(_C))
    w = _fma(builder, vector, w, _const4(_B))
    return _fma(builder, vector, w, _const4(_A))


def _tap_arguments(context, builder, signature, args):
    """The intrinsics' arguments: the data pointer, first tap, strides and the three axes'
    fractional positions."""
    array, start, row_stride, plane_stride, tz, ty, tx = args
    data = context.make_array(signature.args[0])(context, builder, array).data
    return data, start, row_stride, plane_stride, (tz, ty, tx)


def _load_row(builder, data, start, row_stride, plane_stride, a, b):
    """The four x taps of tap row ``(a, b)`` as one ``<4 x float>`` load."""
    plane_start = builder.add(start, builder.mul(plane_stride, ir.Constant(_I64, a)))
    row_start = builder.add(plane_start, builder.mul(row_stride, ir.Constant(_I64, b)))
    address = builder.bitcast(builder.gep(data, [row_start], inbounds=True), _V4.as_pointer())
    return builder.load(address, align=4)


@intrinsic
def taps64(typingctx, flat, offset, row_stride, plane_stride, tz, ty, tx):
    """Tricubic sum over the 4×4×4 taps starting at ``flat[offset]`` (the tap ``(-1, -1, -1)``).

    ``flat`` is the C-ordered float32 coefficient array as 1-D, ``row_stride`` and
    ``plane_stride`` are ``nx`` and ``ny·nx`` (int64), ``tz, ty, tx`` the fractional positions
    (float32, in [0, 1)). No bounds checks: every tap must lie in ``flat``. Returns float32.
    """
    sig = types.float32(flat, offset, row_stride, plane_stride, tz, ty, tx)

    def codegen(context, builder, signature, args):
        data, start, sy, sz, (tz_, ty_, tx_) = _tap_arguments(context, builder, signature, args)
        wz = _weights4(builder, tz_)
        wy = _weights4(builder, ty_)
        wx = _weights4(builder, tx_)
        total = None
        for a in range(4):
            plane = None
            for b in range(4):
                row = _load_row(builder, data, start, sy, sz, a, b)
                weight = _splat(builder, wy, b)
                plane = (
                    builder.fmul(weight, row)
                    if plane is None
                    else _fma(builder, weight, row, plane)
                )
            weight = _splat(builder, wz, a)
            total = (
                builder.fmul(weight, plane)
                if total is None
                else _fma(builder, weight, plane, total)
            )
        return _sum4(builder, builder.fmul(total, wx))

    return sig, codegen


def _derivative_weights4(builder, t):
    """The four taps' weight derivatives ``B + t (2C + t 3D)`` (lane = tap)."""
    vector = builder.insert_element(ir.Constant(_V4, ir.Undefined), t, ir.Constant(_I32, 0))
    vector = _splat(builder, vector, 0)
    w = _fma(builder, vector, _const4([3.0 * d for d in _D]), _const4([2.0 * c for c in _C]))
    return _fma(builder, vector, w, _const4(_B))


def _sum4(builder, vector):
    """The sum of a vector's four lanes, as a float32 scalar."""
    mask = ir.Constant(ir.VectorType(_I32, 4), [2, 3, 2, 3])
    vector = builder.fadd(
        vector, builder.shuffle_vector(vector, ir.Constant(_V4, ir.Undefined), mask)
    )
    mask = ir.Constant(ir.VectorType(_I32, 4), [1, 1, 1, 1])
    vector = builder.fadd(
        vector, builder.shuffle_vector(vector, ir.Constant(_V4, ir.Undefined), mask)
    )
    return builder.extract_element(vector, ir.Constant(_I32, 0))


@intrinsic
def taps64_with_gradient(typingctx, flat, offset, row_stride, plane_stride, tz, ty, tx):
    """:func:`taps64` and the interpolant's gradient from the same 16 row loads.

    Returns the float32 tuple ``(value, d/dz, d/dy, d/dx)``: per plane the y-weighted rows and
    their y-derivative, per volume the z-weighted planes, their z-derivative and the
    y-derivative's z-weighted sum, then one x-dot each (the x-derivative from the value's).
    """
    sig = types.UniTuple(types.float32, 4)(flat, offset, row_stride, plane_stride, tz, ty, tx)

    def codegen(context, builder, signature, args):
        data, start, sy, sz, (tz_, ty_, tx_) = _tap_arguments(context, builder, signature, args)
        wz = _weights4(builder, tz_)
        wy = _weights4(builder, ty_)
        wx = _weights4(builder, tx_)
        dz = _derivative_weights4(builder, tz_)
        dy = _derivative_weights4(builder, ty_)
        dx = _derivative_weights4(builder, tx_)
        total = total_dz = total_dy = None
        for a in range(4):
            plane = plane_dy = None
            for b in range(4):
                row = _load_row(builder, data, start, sy, sz, a, b)
                weight = _splat(builder, wy, b)
                slope = _splat(builder, dy, b)
                if plane is None:
                    plane = builder.fmul(weight, row)
                    plane_dy = builder.fmul(slope, row)
                else:
                    plane = _fma(builder, weight, row, plane)
                    plane_dy = _fma(builder, slope, row, plane_dy)
            weight = _splat(builder, wz, a)
            slope = _splat(builder, dz, a)
            if total is None:
                total = builder.fmul(weight, plane)
                total_dz = builder.fmul(slope, plane)
                total_dy = builder.fmul(weight, plane_dy)
            else:
                total = _fma(builder, weight, plane, total)
                total_dz = _fma(builder, slope, plane, total_dz)
                total_dy = _fma(builder, weight, plane_dy, total_dy)
        values = [
            _sum4(builder, builder.fmul(total, wx)),
            _sum4(builder, builder.fmul(total_dz, wx)),
            _sum4(builder, builder.fmul(total_dy, wx)),
            _sum4(builder, builder.fmul(total, dx)),
        ]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen


@njit(inline="always", **KERNEL_OPTIONS)
def _first_tap(plane_stride, row_stride, z, y, x):
    """Flat index of the tap ``(-1, -1, -1)`` of an interior position and its fractions
    (float32)."""
    iz = int(z)
    iy = int(y)
    ix = int(x)
    start = (iz - 1) * plane_stride + (iy - 1) * row_stride + ix - 1
    return start, np.float32(z - iz), np.float32(y - iy), np.float32(x - ix)


@njit(inline="always", **KERNEL_OPTIONS)
def sample_with_gradient_interior_vector(flat, plane_stride, row_stride, z, y, x):
    """Value and gradient ``(v, dz, dy, dx)`` at ``(z, y, x)`` by :func:`taps64_with_gradient`
    (float32); requires :func:`.interpolation.in_interior`. Equals
    :func:`.interpolation.sample_with_gradient_point` to float32 rounding."""
    start, tz, ty, tx = _first_tap(plane_stride, row_stride, z, y, x)
    return taps64_with_gradient(flat, start, row_stride, plane_stride, tz, ty, tx)


@njit(inline="always", **KERNEL_OPTIONS)
def sample_interior_vector(flat, plane_stride, row_stride, z, y, x):
    """Value at ``(z, y, x)`` by :func:`taps64`; requires :func:`.interpolation.in_interior`.

    ``flat`` is the coefficient volume as 1-D (``coefficients.reshape(coefficients.size)``),
    ``plane_stride = ny·nx`` and ``row_stride = nx``. Equals
    :func:`.interpolation.sample_interior` to float32 rounding.
    """
    start, tz, ty, tx = _first_tap(plane_stride, row_stride, z, y, x)
    return taps64(flat, start, row_stride, plane_stride, tz, ty, tx)
