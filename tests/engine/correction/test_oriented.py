"""Band-oriented re-matches: the plane from the field, the windows, the grouped weighted runs."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction import oriented, oriented_deblur
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import (
    WINDOW_TRUNCATE,
    CorrelationParams,
    gaussian_window,
)
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.progress import run_to_completion

NORMAL = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)


def _field_of(function, shape=(9, 9, 9), step=6.0, origin=10.0) -> DisplacementField:
    axes = [origin + step * np.arange(n) for n in shape]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    u = function(points).reshape(*shape, 3)
    return DisplacementField(origin=(origin,) * 3, step=(step,) * 3, u=u)


def _angle(a, b) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0)))


def test_window_with_equal_stds_is_the_isotropic_window():
    w = oriented.oriented_window(7, (0.3, -0.2, 0.9), 3.0, 3.0)
    np.testing.assert_allclose(w, gaussian_window(7, 3.0, WINDOW_TRUNCATE), rtol=1e-12, atol=0)
    whole = oriented.oriented_window(7, (0.3, -0.2, 0.9), 3.0, 3.0, truncate=None)
    np.testing.assert_allclose(whole, gaussian_window(7, 3.0), rtol=1e-12, atol=0)


def test_window_is_truncated_at_window_truncate_stds():
    """The step's window (std 2 across, 12 along, 31³ box): 0 outside the ellipsoid of 3 std,
    so the matcher skips the 18 of 31 slices beyond ±6 voxels across the plane and more."""
    w = oriented.oriented_window(15, (0.0, 0.0, 1.0), 2.0, 12.0)
    whole = oriented.oriented_window(15, (0.0, 0.0, 1.0), 2.0, 12.0, truncate=None)
    kept = w > 0
    np.testing.assert_array_equal(np.any(kept, axis=(0, 1)), np.abs(np.arange(-15, 16)) <= 6)
    # the in-plane corners lie within 3 std along (15·√2 < 36): the plane's slice is whole
    assert kept[:, :, 15].all()
    assert kept.sum() < 0.36 * kept.size  # 10 549 of 29 791 voxels
    np.testing.assert_array_equal(w[kept], whole[kept])
    # what the cut drops weighs < 1 % of the window in its box (0.55 %: the tails beyond 3 std)
    assert whole[~kept].sum() < 0.01 * whole.sum()
    # an oblique normal: the ellipsoid t²/2² + p²/12² <= 3²
    w = oriented.oriented_window(15, NORMAL, 2.0, 12.0)
    r = np.arange(-15, 16, dtype=np.float64)
    z, y, x = np.meshgrid(r, r, r, indexing="ij")
    t = z * NORMAL[0] + y * NORMAL[1] + x * NORMAL[2]
    r2 = t**2 / 4.0 + (z * z + y * y + x * x - t * t) / 144.0
    # (voxels on the ellipsoid itself fall either side by rounding)
    assert np.all(r2[w > 0] <= 9.0 + 1e-9) and np.all(r2[w == 0] >= 9.0 - 1e-9)


def test_window_is_narrow_across_and_wide_along():
    w = oriented.oriented_window(10, (0.0, 0.0, 1.0), 2.0, 8.0)
    # along x (the normal) it falls with std 2, along y with std 8
    assert w[10, 10, 14] == pytest.approx(np.exp(-16 / 8.0))
    assert w[10, 14, 10] == pytest.approx(np.exp(-16 / 128.0))


@pytest.mark.parametrize(
    "bad",
    [
        dict(normal=(0.0, 0.0, 0.0)), dict(across=0.0), dict(along=np.nan), dict(half=0),
        dict(truncate=0.0), dict(truncate=np.inf),
    ],
)  # fmt: skip
def test_window_refuses_bad_input(bad):
    arguments = dict(half=5, normal=(1.0, 0.0, 0.0), across=2.0, along=6.0) | bad
    with pytest.raises(ValueError):
        oriented.oriented_window(**arguments)


def test_directions_cover_the_sphere_within_the_tolerance():
    directions = oriented.direction_set(4.0)
    rng = np.random.default_rng(0)
    probes = rng.standard_normal((20000, 3))
    probes /= np.linalg.norm(probes, axis=1, keepdims=True)
    nearest = directions[oriented.quantise(probes, directions)]
    assert _angle(probes, nearest).max() < 4.0
    assert np.all(directions[:, 0] >= 0.0)
    with pytest.raises(ValueError):
        oriented.direction_set(0.1)


def test_quantise_in_parts_is_the_nearest_direction_of_all():
    """Thousands of normals (several parts of QUANTISE_ROWS), some NaN: each gets the direction
    of largest |cosine| over the whole set, NaN ones -1, in the normals' shape."""
    directions = oriented.direction_set(4.0)
    rng = np.random.default_rng(1)
    normals = rng.standard_normal((7, 700, 3))
    normals[2, 5:9] = np.nan
    index = oriented.quantise(normals, directions)
    assert index.shape == (7, 700) and oriented.QUANTISE_ROWS < index.size
    expected = np.argmax(np.abs(normals.reshape(-1, 3) @ directions.T), axis=1).reshape(7, 700)
    finite = np.all(np.isfinite(normals), axis=-1)
    np.testing.assert_array_equal(index[finite], expected[finite])
    assert np.all(index[~finite] == -1) and (~finite).sum() == 4


@pytest.mark.parametrize("normal", [NORMAL, np.array([0.2, 0.9, -0.4])])
def test_plane_of_a_band_with_rotation_and_bending_is_recovered(normal):
    normal = normal / np.linalg.norm(normal)
    direction = np.cross(normal, [0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else [1.0, 0, 0]
    truth = synthetic.band_rotation_bending(
        (34.0,) * 3, 6.0, 2.8, normal=tuple(normal), direction=tuple(direction)
    )
    field = _field_of(truth)
    normals, planarity, strength = oriented.plane_normals(field)
    points = field.points.reshape(-1, 3)
    near = (np.abs((points - 34.0) @ normal) < 12.0).reshape(field.shape)
    # the bending's gradient departs from its regional mean only near the grid's border (the
    # mean is not linear there): measured medians 1.6° / 4.6°, 90th percentiles 4.0° / 8.2°
    assert np.median(_angle(normals[near], normal)) < 5.0
    assert np.percentile(_angle(normals[near], normal), 90) < 9.0
    assert np.median(planarity[near]) > 0.9


def test_affine_field_has_no_plane():
    gradient = np.array([[0.02, 0.01, 0.0], [0.0, -0.015, 0.01], [0.01, 0.0, 0.02]])
    field = _field_of(synthetic.affine(gradient, (34.0,) * 3, (1.0, 2.0, 3.0)))
    _, _, strength = oriented.plane_normals(field)
    assert strength.max() < 1e-9


def test_plane_refuses_tiny_grids_and_empty_nodes():
    field = _field_of(synthetic.translation((1.0, 0.0, 0.0)), shape=(2, 5, 5))
    with pytest.raises(ValueError, match="at least 3"):
        oriented.plane_normals(field)
    field = _field_of(synthetic.translation((1.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match="no usable node"):
        oriented.plane_normals(field, usable=np.zeros(field.shape, bool))


def _noisy_band(noise: float, seed: int = 3):
    truth = synthetic.shear_band((31.5,) * 3, width=3.0, slip=2.4)
    pattern = lambda s: synthetic.two_phase_volume(s, seed=seed)  # noqa: E731
    reference, deformed = synthetic.make_pair(pattern, (64,) * 3, truth, margin=12)
    sigma = noise * float(np.std(reference))
    reference = synthetic.add_noise(reference, sigma, seed=1)
    deformed = synthetic.add_noise(deformed, sigma, seed=2)
    return reference, deformed, truth


def test_equal_stds_match_as_the_isotropic_window():
    reference, deformed, _ = _noisy_band(0.2)
    params = CorrelationParams(subvolume=15, step=8)
    grid = ((24.0,) * 3, (8.0,) * 3, (2, 2, 2))
    isotropic = correlate(reference, deformed, params.replace(window=3.0), grid=grid)
    # both truncated at WINDOW_TRUNCATE std
    weights = oriented.oriented_window(params.half, NORMAL, 3.0, 3.0)
    explicit = correlate(reference, deformed, params, grid=grid, weights=weights)
    np.testing.assert_allclose(explicit.u, isotropic.u, atol=1e-9)
    np.testing.assert_array_equal(explicit.status, isotropic.status)


def test_oriented_rematch_beats_the_cube_on_a_noisy_band():
    """Nodes across a narrow band under heavy noise: first-order 21³ cubes against the oriented
    re-match from the cubes' own values (the band's true plane), errors against the truth."""
    reference, deformed, truth = _noisy_band(0.6)
    params = CorrelationParams(subvolume=21, step=6)
    grid = ((19.5 + 0.5,) * 3, (6.0,) * 3, (5, 5, 5))
    cubes = correlate(reference, deformed, params, grid=grid)
    target = truth(cubes.points.reshape(-1, 3)).reshape(cubes.u.shape)
    nodes = np.ones(cubes.shape, bool)
    normals = np.broadcast_to(NORMAL, cubes.u.shape)
    matched, runs = run_to_completion(
        oriented.oriented_rematch(
            oriented.ArrayMatcher(reference, deformed), cubes, nodes, normals, params
        )
    )
    direction = runs.direction
    assert np.all(direction == direction.flat[0])  # one plane: one run
    # the run's window, as its own parameters give it (what the deblur takes the blur of)
    k = int(direction.flat[0])
    half = oriented.group_half(oriented.border_room(cubes, reference.shape), nodes, params)
    _, across, along = oriented.oriented_params(params)
    window = oriented.oriented_window(half, oriented.direction_set()[k], across, along)
    assert runs.half == {k: half} and runs.along == along
    np.testing.assert_array_equal(runs.moments[k], oriented_deblur.window_moments(window))
    np.testing.assert_array_equal(runs.node_moments()[0, 0, 0], runs.moments[k])
    ok = np.all(np.isfinite(matched.u), axis=-1)
    assert ok.mean() > 0.9

    def rmse(u):
        return float(np.sqrt(np.mean(np.sum((u - target)[ok] ** 2, axis=-1))))

    assert rmse(matched.u) < 0.75 * rmse(cubes.u)
    # the windows' blur taken out of the matches (the band's curvature across its plane)
    deblurred, taken = oriented.deblur_matches(matched, ok, runs, normals)
    assert taken.mean() > 0.5
    # 0.128 -> 0.120 voxel when written (a 5³ grid: little plane to average the noise over)
    assert rmse(deblurred) < 0.97 * rmse(matched.u)


def test_rematch_refuses_nodes_of_another_grid():
    field = _field_of(synthetic.translation((1.0, 0.0, 0.0)), shape=(3, 3, 3))
    volume = np.zeros((48,) * 3, np.float32)
    with pytest.raises(ValueError, match="grid shape"):
        run_to_completion(
            oriented.oriented_rematch(
                oriented.ArrayMatcher(volume, volume), field, np.ones((2, 2, 2), bool),
                np.zeros((3, 3, 3, 3)), CorrelationParams(subvolume=15, step=6),
            )
        )  # fmt: skip


def test_step_does_not_run_where_the_first_run_s_boxes_follow_the_field():
    """A second-order first run, or no bend above the threshold: nothing is done (and the
    volumes are not touched)."""
    band = _field_of(synthetic.band_rotation_bending((34.0,) * 3, 4.0, 2.8))
    flat = _field_of(synthetic.translation((1.0, 2.0, 0.5)))
    params = CorrelationParams(subvolume=21, step=6)
    for field, first in ((band, params.replace(order=2)), (flat, params)):
        step = run_to_completion(
            oriented.oriented_step(
                None, None, field, None, first, np.zeros(field.shape, bool), None, 1.0,
            )
        )  # fmt: skip
        assert not step.applied and not step.summary["ran"]
        assert step.field is field
