"""Explicit four-wide float32 arithmetic for numba kernels (LLVM vector IR).

numba leaves LLVM's SLP vectorizer off, so four independent sums over contiguous taps stay
scalar. :func:`field_taps` and :func:`field_taps_with_gradient` write the displacement field
spline's evaluation (3 components, and their derivatives) as four-wide loads, multiplies and adds
in LLVM IR instead. The tricubic B-spline sample of a volume, the same idea for one component
with the weights as vector polynomials, is :func:`.simd_taps.taps64`.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic


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
