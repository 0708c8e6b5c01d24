"""Explicit four-wide float32 arithmetic for numba kernels (LLVM vector IR).

numba leaves LLVM's SLP vectorizer off, so four independent sums over contiguous taps stay
scalar. :func:`bspline_value` writes a tricubic B-spline sample's vector loads, multiplies and
adds in LLVM IR instead: 16 four-wide loads of contiguous x taps (about 1.9 times faster than
the scalar ``interpolation.sample_interior``, measured in one process).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic

#: Cubic B-spline weights of the taps at -1 .. 2 as polynomials in the fraction t:
#: ``w = A + t (B + t (C + t D))``.
_BSPLINE_POWERS = (
    (1.0 / 6.0, 4.0 / 6.0, 1.0 / 6.0, 0.0),
    (-0.5, 0.0, 0.5, 0.0),
    (0.5, -1.0, 0.5, 0.0),
    (-1.0 / 6.0, 0.5, -0.5, 1.0 / 6.0),
)


@intrinsic
def bspline_value(typingctx, flat, first, row, plane, fz, fy, fx):
    """Tricubic B-spline value from the 64 taps at ``flat[first + a plane + b row + k]``.

    ``fz, fy, fx`` (float32) are the position's fractions beyond its tap at index 1 of each axis
    (the taps are at -1 .. 2 around it). The weights of each axis are one four-wide polynomial,
    each z plane's 4 rows of 4 contiguous x taps summed four-wide with their y weights (4
    independent chains), the planes with their z weights pairwise, then a dot product with the x
    weights. Equals ``interpolation.sample_interior`` to float32 rounding. No bounds
    checks: the caller keeps every index inside ``flat``.
    """
    sig = types.float32(flat, first, row, plane, fz, fy, fx)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        first, row, plane_stride, fz, fy, fx = args[1:]
        i32 = ir.IntType(32)
        f32 = ir.FloatType()
        v4 = ir.VectorType(f32, 4)
        undefined = ir.Constant(v4, ir.Undefined)

        def lane(vector, k):
            mask = ir.Constant(ir.VectorType(i32, 4), [k, k, k, k])
            return builder.shuffle_vector(vector, undefined, mask)

        def weights(t):
            t = lane(builder.insert_element(undefined, t, ir.Constant(i32, 0)), 0)
            a, b, c, d = (ir.Constant(v4, list(p)) for p in _BSPLINE_POWERS)
            w = builder.fadd(c, builder.fmul(t, d))
            w = builder.fadd(b, builder.fmul(t, w))
            return builder.fadd(a, builder.fmul(t, w))

        wz, wy, wx = weights(fz), weights(fy), weights(fx)
        planes = []
        start = first
        for a in range(4):
            index = start
            plane = None
            for b in range(4):
                pointer = builder.bitcast(builder.gep(data, [index]), v4.as_pointer())
                taps = builder.fmul(lane(wy, b), builder.load(pointer, align=4))
                plane = taps if plane is None else builder.fadd(plane, taps)
                index = builder.add(index, row)
            planes.append(builder.fmul(lane(wz, a), plane))
            start = builder.add(start, plane_stride)
        total = builder.fadd(builder.fadd(planes[0], planes[1]), builder.fadd(planes[2], planes[3]))
        total = builder.fmul(wx, total)
        items = [builder.extract_element(total, ir.Constant(i32, k)) for k in range(4)]
        return builder.fadd(builder.fadd(items[0], items[1]), builder.fadd(items[2], items[3]))

    return sig, codegen
