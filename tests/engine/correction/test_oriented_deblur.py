"""The oriented window's blur taken out of the node field: moments, exact on quadratics, a band."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correction import oriented, oriented_deblur
from napari_dvc_correct.engine.correlation.params import WINDOW_TRUNCATE, gaussian_window

NORMAL = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
STEP = 6.0


def _grid(shape=(9, 9, 9), origin=10.0):
    axes = [origin + STEP * np.arange(n) for n in shape]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


def _moments(normal, across=2.5, along=10.0, half=15, truncate=WINDOW_TRUNCATE):
    return oriented_deblur.window_moments(
        oriented.oriented_window(half, normal, across, along, truncate)
    )


def test_moments_of_gaussian_windows_are_their_variances():
    np.testing.assert_allclose(
        oriented_deblur.window_moments(gaussian_window(12, 2.0)), 4.0 * np.eye(3), atol=1e-9
    )
    # across the x axis std 1.5, along it 3: a box of 7 stds holds the Gaussian to 1e-9 (the
    # whole Gaussian: the step's windows, truncated at 3 std, have their own moments)
    whole = oriented.oriented_window(21, (0, 0, 1), 1.5, 3.0, truncate=None)
    moments = oriented_deblur.window_moments(whole)
    np.testing.assert_allclose(moments, np.diag([9.0, 9.0, 2.25]), atol=1e-8)
    # an inclined normal: the tensor is across² n nᵀ + along² (I − n nᵀ)
    moments = _moments(NORMAL, 1.5, 3.0, half=21, truncate=None)
    expected = 2.25 * np.outer(NORMAL, NORMAL) + 9.0 * (np.eye(3) - np.outer(NORMAL, NORMAL))
    np.testing.assert_allclose(moments, expected, atol=1e-8)


@pytest.mark.parametrize("weights", [np.ones((4, 4, 4)), np.zeros((5, 5, 5)), -np.ones((3,) * 3)])
def test_moments_refuse_bad_weights(weights):
    with pytest.raises(ValueError):
        oriented_deblur.window_moments(weights)


@pytest.mark.parametrize("normal", [NORMAL, np.array([0.2, 0.9, -0.4])])
def test_quadratic_field_blurred_by_the_window_is_restored_exactly(normal):
    """``M = u + tr(Σ H)/2`` holds exactly for a quadratic ``u``; the local quadratic holds it."""
    normal = normal / np.linalg.norm(normal)
    points = _grid()
    rng = np.random.default_rng(1)
    hessians = [(h + h.T) * 0.002 for h in rng.standard_normal((3, 3, 3))]
    linear = rng.standard_normal((3, 3)) * 0.02
    centre = points.reshape(-1, 3).mean(0)
    x = points - centre
    u = np.stack([0.5 * np.einsum("...i,ij,...j", x, h, x) for h in hessians], -1) + x @ linear.T
    moments = np.broadcast_to(_moments(normal), points.shape[:3] + (3, 3))
    blurred = u + np.array([0.5 * np.trace(moments[0, 0, 0] @ h) for h in hessians])
    assert np.abs(blurred - u).max() > 0.1  # the blur is not small
    nodes = np.ones(points.shape[:3], bool)
    normals = np.broadcast_to(normal, points.shape)
    restored, taken = oriented_deblur.deblur_across(
        blurred, points, nodes, normals, moments, STEP, 10.0
    )
    assert taken[2:-2, 2:-2, 2:-2].all()
    np.testing.assert_allclose(restored[taken], u[taken], atol=1e-9)
    np.testing.assert_array_equal(restored[~taken], blurred[~taken])


def _band_profile(t, width=4.0, slip=2.8):
    return 0.5 * slip * np.tanh(t / width)


def test_a_blurred_narrow_band_is_sharpened():
    """A tanh band of half-width 4 blurred across by a Gaussian of std 2.5 (what a first-order
    match under the oriented window reads): the deblurred nodes are nearer the band."""
    points = _grid()
    centre = points.reshape(-1, 3).mean(0)
    t = (points - centre) @ NORMAL
    s = np.linspace(-12.0, 12.0, 2401)
    kernel = np.exp(-0.5 * (s / 2.5) ** 2)
    kernel /= kernel.sum()
    blurred_profile = np.array([kernel @ _band_profile(value - s) for value in t.ravel()])
    truth = np.zeros(points.shape)
    truth[..., 2] = _band_profile(t)
    blurred = np.zeros(points.shape)
    blurred[..., 2] = blurred_profile.reshape(t.shape)
    moments = np.broadcast_to(_moments(NORMAL), points.shape[:3] + (3, 3))
    restored, taken = oriented_deblur.deblur_across(
        blurred, points, np.ones(t.shape, bool), np.broadcast_to(NORMAL, points.shape), moments,
        STEP, 10.0,
    )  # fmt: skip
    band = taken & (np.abs(t) < 8.0)
    before = np.sqrt(np.mean((blurred - truth)[band] ** 2))
    after = np.sqrt(np.mean((restored - truth)[band] ** 2))
    assert before > 0.05
    assert after < 0.65 * before  # 0.067 -> 0.041 voxel when written


def test_noise_is_not_amplified():
    """Pure matching noise (no field): the estimate's scatter is at most the matches'."""
    points = _grid()
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 0.1, points.shape)
    moments = np.broadcast_to(_moments(NORMAL), points.shape[:3] + (3, 3))
    restored, taken = oriented_deblur.deblur_across(
        noise, points, np.ones(points.shape[:3], bool), np.broadcast_to(NORMAL, points.shape),
        moments, STEP, 10.0,
    )  # fmt: skip
    assert taken.mean() > 0.5
    assert np.std(restored[taken]) < np.std(noise[taken])


def test_isolated_nodes_keep_their_match_and_bad_input_is_refused():
    points = _grid((3, 3, 3))
    u = np.random.default_rng(0).normal(size=points.shape)
    nodes = np.zeros((3, 3, 3), bool)
    nodes[1, 1, 1] = True
    moments = np.broadcast_to(_moments(NORMAL), (3, 3, 3, 3, 3))
    normals = np.broadcast_to(NORMAL, points.shape)
    restored, taken = oriented_deblur.deblur_across(u, points, nodes, normals, moments, 6, 10.0)
    assert not taken.any()
    np.testing.assert_array_equal(restored, u)
    with pytest.raises(ValueError):
        oriented_deblur.deblur_across(u[..., :2], points, nodes, normals, moments, 6, 10.0)
    with pytest.raises(ValueError):
        oriented_deblur.deblur_across(u, points, nodes[:2], normals, moments, 6, 10.0)
    with pytest.raises(ValueError):
        oriented_deblur.deblur_across(u, points, nodes, normals, moments, 6, 0.0)


def _deblur_loop(u, points, nodes, normals, moments, step, along):
    """The per-node loop :func:`.oriented_deblur.deblur_across` ran before its kernel (numpy,
    line for line), with why each node kept its match: the reference of the kernel."""
    columns = 10
    nodes = nodes & np.all(np.isfinite(u), axis=-1)
    step = np.broadcast_to(np.asarray(step, np.float64), (3,))
    across_reach = oriented_deblur.ACROSS_REACH * float(step.min())
    along_reach = oriented_deblur.ALONG_REACH * float(along)
    radius = np.ceil(np.sqrt(-2.0 * np.log(oriented_deblur.MIN_WEIGHT)) * along_reach / step)
    radius = radius.astype(int)
    deblurred, taken, reasons = u.copy(), np.zeros(u.shape[:3], bool), []
    for index in zip(*np.nonzero(nodes)):
        box = tuple(
            slice(max(i - r, 0), min(i + r + 1, n)) for i, r, n in zip(index, radius, u.shape)
        )
        data = nodes[box]
        offsets = points[box][data] - points[index]
        normal = normals[index] / np.linalg.norm(normals[index])
        helper = np.zeros(3)
        helper[int(np.argmin(np.abs(normal)))] = 1.0
        first = np.cross(normal, helper)
        first /= np.linalg.norm(first)
        frame = np.stack([normal, first, np.cross(normal, first)])
        t, a, b = (offsets @ frame.T).T
        weight = np.exp(-0.5 * (t / across_reach) ** 2 - 0.5 * (a * a + b * b) / along_reach**2)
        keep = weight >= oriented_deblur.MIN_WEIGHT
        if int(keep.sum()) < 2 * columns:
            reasons.append("few")
            continue
        t, a, b, weight = t[keep], a[keep], b[keep], weight[keep]
        design = np.stack([np.ones_like(t), t, a, b, t * t, a * a, b * b, a * b, t * a, t * b], 1)
        root = np.sqrt(weight)[:, None]
        normal_matrix = (design * root).T @ (design * root)
        sigma = frame @ moments[index] @ frame.T
        read = np.array(
            [1.0, 0, 0, 0, -sigma[0, 0], -sigma[1, 1], -sigma[2, 2],
             -sigma[1, 2], -sigma[0, 1], -sigma[0, 2]]
        )  # fmt: skip
        try:
            solved = np.linalg.solve(normal_matrix, read)
        except np.linalg.LinAlgError:
            reasons.append("singular")
            continue
        if not np.all(np.isfinite(solved)) or np.linalg.cond(normal_matrix) > 1e12:
            reasons.append("singular")
            continue
        linear = (design @ solved) * weight
        if float(np.linalg.norm(linear)) > oriented_deblur.MAX_NOISE_GAIN:
            reasons.append("gain")
            continue
        deblurred[index] = linear @ u[box][data][keep]
        taken[index] = True
        reasons.append("taken")
    return deblurred, taken, reasons


def _random_case(seed, shape, share, along):
    """A field with a band, noise, every node its own normal (±20° about one plane) and its
    own window; ``share`` of the nodes hold a match."""
    rng = np.random.default_rng(seed)
    points = _grid(shape) + rng.uniform(-0.5, 0.5, shape + (3,))
    centre = points.reshape(-1, 3).mean(0)
    t = (points - centre) @ NORMAL
    u = np.stack([_band_profile(t), 0.01 * t**2 / 6.0, 0.3 + 0.02 * t], -1)
    u = u + rng.normal(0.0, 0.05, u.shape)
    normals = NORMAL + rng.normal(0.0, 0.25, u.shape)
    spread = rng.normal(0.0, 1.0, shape + (3, 3))
    moments = spread @ np.swapaxes(spread, -1, -2) + along**2 * np.eye(3) / 4.0
    nodes = rng.random(shape) < share
    return u, points, nodes, normals, moments


@pytest.mark.parametrize(
    "seed, shape, share, along, step",
    [
        (0, (9, 10, 11), 0.85, 10.0, STEP),  # inner nodes taken, faces' gain refused
        (1, (7, 8, 9), 0.3, 6.0, STEP),  # few neighbours
        (2, (2, 12, 13), 1.0, 10.0, STEP),  # two layers across: no quadratic across
        (3, (6, 7, 8), 0.9, 12.0, (6.0, 5.0, 7.0)),  # uneven step
    ],
)
def test_the_kernel_gives_the_loop_s_numbers(seed, shape, share, along, step):
    """Against the former per-node loop on random cases, fall-backs included: the same nodes
    taken, the same values to 1e-12 relative (rounding of the sums' order)."""
    u, points, nodes, normals, moments = _random_case(seed, shape, share, along)
    if shape[0] == 2:  # the layers exactly planar, across their plane
        points, normals = _grid(shape), np.broadcast_to((1.0, 0.0, 0.0), u.shape)
    u[tuple(np.argwhere(nodes)[0])] = np.nan  # a failed match is neither datum nor deblurred
    expected, expected_taken, reasons = _deblur_loop(
        u, points, nodes, normals, moments, step, along
    )
    restored, taken = oriented_deblur.deblur_across(u, points, nodes, normals, moments, step, along)
    np.testing.assert_array_equal(taken, expected_taken)
    scale = np.abs(u[taken]).max(initial=1.0)
    np.testing.assert_allclose(restored, expected, rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(restored[~taken], u[~taken])
    counts = {reason: reasons.count(reason) for reason in set(reasons)}
    if seed == 0:
        assert counts["taken"] > 100 and counts["gain"] > 5, counts
    if seed == 1:
        assert counts["few"] > 5, counts
    if seed == 2:
        assert counts == {"singular": int(np.isfinite(u).all(-1)[nodes].sum())}, counts
