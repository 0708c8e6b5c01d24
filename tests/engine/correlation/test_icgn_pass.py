"""The IC-GN sampling pass (chunked, vector tap sums) against sums over the scalar sampler."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.icgn_pass import sample_pass
from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample
from napari_dvc_correct.engine.synthetic import textured_volume


def _subvolume(half, center):
    axes = np.arange(-half, half + 1)
    xi = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(3)
    g = rng.normal(100.0, 10.0, len(xi)).astype(np.float32)
    grad = rng.normal(0.0, 5.0, (len(xi), 3)).astype(np.float32)
    return g, grad, xi.astype(np.float32)


def _expected(coef, g, grad, xi, center, p, nb):
    x = xi.astype(np.float64)
    b = [np.ones(len(x)), x[:, 0], x[:, 1], x[:, 2]]
    if nb == 10:
        z, y, w = x.T
        b += [z * z, y * y, w * w, z * y, y * w, z * w]
    b = np.array(b)  # (nb, n)
    position = center + x + (p.reshape(3, nb) @ b).T
    f = sample(coef, position).astype(np.float64)
    dg = g - g.mean()
    sum_jf = (grad.astype(np.float64).T[:, None, :] * b[None] * f).sum(-1).reshape(-1)
    return f.sum(), (f * f).sum(), (dg * f).sum(), sum_jf


@pytest.mark.parametrize("nb", [4, 10])
# interior, and next to two faces (z near 0.5, x near n - 1.5: the mirrored taps)
@pytest.mark.parametrize("center", [(20, 20, 20), (6, 20, 32)])
def test_sample_pass_equals_the_sums_over_the_scalar_sampler(nb, center):
    coef = prefilter(textured_volume((40, 41, 39), 2.0, 1) * 100.0)
    g, grad, xi = _subvolume(5, center)
    rng = np.random.default_rng(nb)
    p = np.zeros(3 * nb)
    p[::nb] = (-0.45, rng.uniform(-0.6, 0.6), 0.45)
    for k in range(3):
        p[k * nb + 1 : k * nb + 4] = rng.uniform(-0.03, 0.03, 3)
        if nb == 10:
            p[k * nb + 4 : k * nb + 10] = rng.uniform(-0.003, 0.003, 6)
    outside = np.zeros(len(g), np.bool_)
    sum_jf = np.zeros(3 * nb)
    center = np.array(center, np.int64)
    result = sample_pass(
        coef, g, grad, xi, len(g), float(g.mean()), *center, p, nb, outside, sum_jf
    )
    sum_f, sum_ff, sum_gf, sum_jf_e = _expected(coef, g, grad, xi, center, p, nb)
    assert result[3] == 0 and not outside.any()
    if center[0] == 6:  # the border case reaches the mirrored taps
        assert (center[0] + xi[:, 0] + p[0] - 0.2 < 1.0).any()
    # float32 samples (vector and scalar tap sums differ by float32 rounding): 1e-6 relative
    np.testing.assert_allclose(result[:3], (sum_f, sum_ff, sum_gf), rtol=1e-6, atol=1e-3)
    np.testing.assert_allclose(sum_jf, sum_jf_e, rtol=1e-6, atol=1e-6 * np.abs(sum_jf_e).max())


def test_voxels_warped_outside_are_flagged_and_counted():
    coef = prefilter(textured_volume((30, 30, 30), 2.0, 2))
    g, grad, xi = _subvolume(4, (5, 15, 15))
    p = np.zeros(12)
    p[0] = -2.5  # planes dz = -4, -3 land below z = 0
    outside = np.zeros(len(g), np.bool_)
    result = sample_pass(
        coef, g, grad, xi, len(g), float(g.mean()), 5, 15, 15, p, 4, outside, np.zeros(12)
    )
    expected = 5 + xi[:, 0] - 2.5 < 0.0
    assert result[3] == expected.sum() == 2 * 81
    np.testing.assert_array_equal(outside, expected)
