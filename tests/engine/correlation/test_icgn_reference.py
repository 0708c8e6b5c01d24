"""The reference side of IC-GN: the fused first- and second-order passes against the definitions."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation import icgn_reference


def _subvolume(half=3, seed=0, drop=0):
    rng = np.random.default_rng(seed)
    axes = np.arange(-half, half + 1)
    xi = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), -1).reshape(-1, 3)
    keep = np.ones(len(xi), bool)
    keep[rng.choice(len(xi), drop, replace=False)] = False  # masked voxels: ragged rows
    xi = xi[keep]
    g = (1000.0 + 50.0 * rng.standard_normal(len(xi))).astype(np.float32)
    grad = (20.0 * rng.standard_normal((len(xi), 3))).astype(np.float32)
    return g, grad, xi.astype(np.float32)


def _definition(g, grad, xi, order=1):
    """Mean, norm, ``H = JᵀJ``, ``Σ J`` and ``Σ J (g − ḡ)`` with ``J = ∇G ⊗ b(ξ)`` written out."""
    g = g.astype(np.float64)
    z, y, x = xi.astype(np.float64).T
    columns = [np.ones(len(xi)), z, y, x]
    if order == 2:  # the monomials' order of shape_function.monomials
        columns += [z * z, y * y, x * x, z * y, y * x, z * x]
    b = np.column_stack(columns)
    jac = (grad.astype(np.float64)[:, :, None] * b[:, None, :]).reshape(len(g), 3 * b.shape[1])
    dg = g - g.mean()
    return g.mean(), np.sqrt(dg @ dg), jac.T @ jac, jac.sum(0), jac.T @ dg


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("half, drop", [(3, 0), (3, 40), (7, 300)])
def test_reference_terms_equal_their_definitions_with_and_without_masked_voxels(order, half, drop):
    # second order sums x-rows times 1 ... x⁴ and folds them into the 35 quartic moments: the
    # larger subvolume checks that the moments keep float64 accuracy at |x|⁴ = 2401
    g, grad, xi = _subvolume(half=half, drop=drop)
    mean_g, delta_g, ok, low, sum_j, sum_jg = icgn_reference.reference_terms(
        g, grad, xi, len(g), 4 if order == 1 else 10
    )
    mean_e, delta_e, hessian_e, sum_j_e, sum_jg_e = _definition(g, grad, xi, order)
    assert ok
    np.testing.assert_allclose(mean_g, mean_e, rtol=1e-12)
    np.testing.assert_allclose(delta_g, delta_e, rtol=1e-10)
    np.testing.assert_allclose(low @ low.T, hessian_e, rtol=1e-9, atol=1e-9 * hessian_e.max())
    scale = np.abs(sum_j_e).max()
    np.testing.assert_allclose(sum_j, sum_j_e, rtol=1e-10, atol=1e-10 * scale)
    np.testing.assert_allclose(sum_jg, sum_jg_e, rtol=1e-10, atol=1e-10 * np.abs(sum_jg_e).max())


def test_float32_and_float64_copies_give_the_same_terms():
    g, grad, xi = _subvolume(seed=4, drop=7)
    single = icgn_reference.reference_terms(g, grad, xi, len(g), 4)
    double = icgn_reference.reference_terms(
        g.astype(np.float64), grad.astype(np.float64), xi.astype(np.float64), len(g), 4
    )
    for a, b in zip(single, double):
        np.testing.assert_array_equal(a, b)


def _stencil_gradient(coefficients):
    """The 3×3×3 stencil written out: value weights (1, 4, 1) / 6, derivative (-1, 0, 1) / 2."""
    padded = np.pad(coefficients.astype(np.float64), 1, mode="reflect")  # scipy's "mirror"
    value = np.array([1.0, 4.0, 1.0]) / 6.0
    deriv = np.array([-0.5, 0.0, 0.5])
    nz, ny, nx = coefficients.shape
    out = np.zeros((3, nz, ny, nx))
    for a in range(3):
        for b in range(3):
            for c in range(3):
                taps = padded[a : a + nz, b : b + ny, c : c + nx]
                out[0] += deriv[a] * value[b] * value[c] * taps
                out[1] += value[a] * deriv[b] * value[c] * taps
                out[2] += value[a] * value[b] * deriv[c] * taps
    return out


@pytest.mark.parametrize("shape", [(19, 6, 7), (3, 2, 9), (1, 5, 4), (17, 17, 17)])
def test_gradient_volume_is_the_stencil_and_the_interpolants_derivative(shape):
    from scipy import ndimage

    from napari_dvc_correct.engine.correlation.interpolation import prefilter

    rng = np.random.default_rng(1)
    volume = ndimage.gaussian_filter(rng.normal(100.0, 20.0, shape), 1.0).astype(np.float32)
    coefficients = prefilter(volume)
    gradient = icgn_reference.gradient_volume(coefficients)
    assert gradient.dtype == np.float32 and gradient.shape == (3, *shape)
    expected = _stencil_gradient(coefficients)
    np.testing.assert_allclose(gradient, expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())
    # against the known answer: central differences of scipy's cubic spline (mirror) at interior
    # voxels of the larger volumes
    if min(shape) >= 5:
        h = 1e-3
        points = np.stack(np.meshgrid(*[np.arange(1, n - 1) for n in shape], indexing="ij"))
        points = points.reshape(3, -1).astype(np.float64)
        for axis in range(3):
            step = np.zeros((3, 1))
            step[axis] = h
            up, down = (
                ndimage.map_coordinates(
                    volume.astype(np.float64), points + sign * step, order=3, mode="mirror"
                )  # fmt: skip
                for sign in (1.0, -1.0)
            )
            numeric = (up - down) / (2 * h)
            inner = gradient[axis][tuple(slice(1, n - 1) for n in shape)].reshape(-1)
            np.testing.assert_allclose(inner, numeric, atol=1e-3 * np.abs(numeric).max())


@pytest.mark.parametrize("shape", [(13, 9, 11), (7, 7, 7), (5, 12, 6)])
def test_a_subvolumes_gradient_equals_the_volumes_bit_for_bit(shape):
    """Every subvolume's ``∇G`` computed alone, at the faces (mirrored taps) and inside, is the
    whole volume's there to the last bit; ``gradient_source`` reads either form."""
    from napari_dvc_correct.engine.correlation.interpolation import prefilter

    rng = np.random.default_rng(3)
    volume = (1000.0 * rng.random(shape)).astype(np.uint16)
    coefficients = prefilter(volume)
    whole = icgn_reference.gradient_volume(coefficients)
    for half in (1, 2):
        for cz in range(half, shape[0] - half):
            for cy in range(half, shape[1] - half):
                for cx in range(half, shape[2] - half):
                    window = (slice(None),) + tuple(
                        slice(c - half, c + half + 1) for c in (cz, cy, cx)
                    )
                    block = icgn_reference.subvolume_gradient(coefficients, cz, cy, cx, half)
                    assert block.dtype == np.float32
                    np.testing.assert_array_equal(
                        block.view(np.uint32), whole[window].view(np.uint32)
                    )
    source, *offsets = icgn_reference.gradient_source(whole, 3, 3, 3, 2)
    assert source is whole and offsets == [0, 0, 0]
    source, *offsets = icgn_reference.gradient_source(coefficients[None], 2, 4, 2, 2)
    assert offsets == [0, 2, 0]
    np.testing.assert_array_equal(source, whole[:, 0:5, 2:7, 0:5])
