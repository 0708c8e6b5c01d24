"""Explicit four-wide float32 arithmetic for numba kernels (LLVM vector IR).

numba leaves LLVM's SLP vectorizer off, so four independent sums over contiguous taps stay
scalar. :func:`rows16` writes the vector loads, multiplies and adds in LLVM IR instead (no fused
multiply-add: each lane rounds as the same scalar sums in the same order would).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic


@intrinsic
def rows16(typingctx, flat, first, row, plane, wz, wy):
    """``s[k] = sum over a, b of wz[a] wy[b] flat[first + a plane + b row + k]``, k = 0 .. 3.

    For a tricubic B-spline: the 4 x-tap columns of a point's 4 × 4 (z, y) rows, 4 contiguous
    taps per vector load. Each z plane's 4 rows are summed with their y weights (4 independent
    chains), then the planes with their z weights, pairwise.

    Parameters
    ----------
    flat : 1-D C-contiguous float32 array
        The coefficients in C order.
    first, row, plane : uint64
        Flat index of the first tap, and the strides (elements) of y and z.
    wz, wy : tuple of 4 float32
        Weights along z and y.

    Returns
    -------
    tuple of 4 float32
        The column sums. No bounds checks: the caller keeps every index inside ``flat``.
    """
    sig = types.UniTuple(types.float32, 4)(flat, first, row, plane, wz, wy)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        first, row, plane_stride, wz, wy = args[1:]
        i32 = ir.IntType(32)
        v4 = ir.VectorType(ir.FloatType(), 4)
        undefined = ir.Constant(v4, ir.Undefined)
        broadcast = ir.Constant(ir.VectorType(i32, 4), [0, 0, 0, 0])

        def splat(value):
            lanes = builder.insert_element(undefined, value, ir.Constant(i32, 0))
            return builder.shuffle_vector(lanes, undefined, broadcast)

        planes = []
        start = first
        for a in range(4):
            index = start
            plane = None
            for b in range(4):
                pointer = builder.bitcast(builder.gep(data, [index]), v4.as_pointer())
                taps = builder.fmul(
                    splat(builder.extract_value(wy, b)), builder.load(pointer, align=4)
                )
                plane = taps if plane is None else builder.fadd(plane, taps)
                index = builder.add(index, row)
            planes.append(builder.fmul(splat(builder.extract_value(wz, a)), plane))
            start = builder.add(start, plane_stride)
        total = builder.fadd(builder.fadd(planes[0], planes[1]), builder.fadd(planes[2], planes[3]))
        items = [builder.extract_element(total, ir.Constant(i32, k)) for k in range(4)]
        return context.make_tuple(builder, signature.return_type, items)

    return sig, codegen
