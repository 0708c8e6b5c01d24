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


def _splat(builder, vector_type, value):
    i32 = ir.IntType(32)
    lanes = builder.insert_element(ir.Constant(vector_type, ir.Undefined), value, i32(0))
    mask = ir.Constant(ir.VectorType(i32, vector_type.count), [0] * vector_type.count)
    return builder.shuffle_vector(lanes, ir.Constant(vector_type, ir.Undefined), mask)


def _pack(builder, vector_type, values):
    vector = ir.Constant(vector_type, ir.Undefined)
    for k, value in enumerate(values):
        vector = builder.insert_element(vector, value, ir.IntType(32)(k))
    return vector


def _sum_lanes(builder, vector):
    i32 = ir.IntType(32)
    items = [builder.extract_element(vector, i32(k)) for k in range(4)]
    return builder.fadd(builder.fadd(items[0], items[1]), builder.fadd(items[2], items[3]))


def _weighted(builder, vectors, weights):
    """``sum_k weights[k] * vectors[k]`` (vectors), pairwise."""
    terms = [builder.fmul(w, v) for w, v in zip(weights, vectors)]
    return builder.fadd(builder.fadd(terms[0], terms[1]), builder.fadd(terms[2], terms[3]))


def _field_codegen(gradient):
    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        first, row, plane, component = args[1:5]
        v4 = ir.VectorType(ir.DoubleType(), 4)

        def scalars(pack):
            return [builder.extract_value(pack, k) for k in range(4)]

        wz, wy, wx = (scalars(pack) for pack in args[5:8])
        sz, sy = ([_splat(builder, v4, w) for w in weights] for weights in (wz, wy))
        wx_vector = _pack(builder, v4, wx)
        if gradient:
            dz, dy, dx = (scalars(pack) for pack in args[8:11])
            tz, ty = ([_splat(builder, v4, w) for w in weights] for weights in (dz, dy))
            dx_vector = _pack(builder, v4, dx)
        values, grad_z, grad_y, grad_x = [], [], [], []
        base = first
        for _ in range(3):
            plane_values, plane_dy = [], []
            start = base
            for _a in range(4):
                rows = []
                index = start
                for _b in range(4):
                    pointer = builder.bitcast(builder.gep(data, [index]), v4.as_pointer())
                    rows.append(builder.load(pointer, align=8))
                    index = builder.add(index, row)
                plane_values.append(_weighted(builder, rows, sy))
                if gradient:
                    plane_dy.append(_weighted(builder, rows, ty))
                start = builder.add(start, plane)
            along_z = _weighted(builder, plane_values, sz)
            values.append(_sum_lanes(builder, builder.fmul(wx_vector, along_z)))
            if gradient:
                grad_z.append(
                    _sum_lanes(
                        builder, builder.fmul(wx_vector, _weighted(builder, plane_values, tz))
                    )
                )
                grad_y.append(
                    _sum_lanes(builder, builder.fmul(wx_vector, _weighted(builder, plane_dy, sz)))
                )
                grad_x.append(_sum_lanes(builder, builder.fmul(dx_vector, along_z)))
            base = builder.add(base, component)
        items = values + grad_z + grad_y + grad_x
        return context.make_tuple(builder, signature.return_type, items)

    return codegen


@intrinsic
def field_taps(typingctx, flat, first, row, plane, component, wz, wy, wx):
    """A 3-component tricubic spline's taps weighted: ``(v0, v1, v2)`` (float64).

    ``flat`` holds the coefficients component-major, ``(3, nz, ny, nx)``, C-contiguous float64
    (any number of dimensions: only its data pointer is used, no view is made per call);
    ``first`` is the flat index of component 0's first tap, ``row``, ``plane`` and ``component``
    (uint64) the strides of y, z and the component; ``wz, wy, wx`` the 4 weights per axis
    (tuples of float64). Four-wide loads of the 4 contiguous x taps; each z plane's rows summed
    with their y weights pairwise, the planes with their z weights, then the x weights. No
    bounds checks.
    """
    sig = types.UniTuple(types.float64, 3)(flat, first, row, plane, component, wz, wy, wx)
    return sig, _field_codegen(False)


@intrinsic
def field_taps_with_gradient(typingctx, flat, first, row, plane, component, wz, wy, wx, dz, dy, dx):
    """:func:`field_taps` and the derivative sums: 12 float64, ``v0..2``, then ``d/dz``,
    ``d/dy``, ``d/dx`` of each component (``dz, dy, dx``: the derivative weights per axis)."""
    args = (flat, first, row, plane, component, wz, wy, wx, dz, dy, dx)
    sig = types.UniTuple(types.float64, 12)(*args)
    return sig, _field_codegen(True)
