"""Outlier detection, inpainting and cleaning (engine/correction/cleaning.py) with known answers."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction import cleaning
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status

ORIGIN, STEP, SHAPE = (10.0, 10.0, 10.0), (4.0, 4.0, 4.0), (14, 15, 16)
SMOOTH = synthetic.shear_band(
    (36.0, 38.0, 40.0), width=12.0, slip=6.0, shift=(2.0, -3.0, 4.0), background_strain=0.02
)
GRADIENT = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])


def _grid_field(function, shape=SHAPE):
    field = DisplacementField.zeros(ORIGIN, STEP, shape)
    field.u[:] = synthetic.sample_displacement(function, field.points.reshape(*shape, 3))
    return field


def _holes(shape=SHAPE, seed=1):
    rng = np.random.default_rng(seed)
    known = rng.random(shape) > 0.1  # scattered single nodes
    known[4:7, 5:8, 6:9] = False  # a block of 27 nodes
    known[0:2, 0:3, 0:3] = False  # a corner: the hole touches the grid's border
    known[:, 10, 12] = False  # a line through the whole grid
    return known


def test_inpainting_reproduces_a_smooth_field_at_removed_nodes():
    truth = _grid_field(SMOOTH).u
    known = _holes()
    filled = cleaning.inpaint(np.where(known[..., None], truth, np.nan), known, STEP)
    assert (~known).sum() > 300
    assert np.abs(filled - truth)[~known].max() < 0.05
    assert np.array_equal(filled[known], truth[known])


def test_inpainting_is_exact_for_affine_fields_small_and_large_holes():
    affine = synthetic.affine(GRADIENT, (30.0, 30.0, 30.0), (1.0, 2.0, 3.0))
    truth = _grid_field(affine).u
    known = _holes()
    filled = cleaning.inpaint(np.where(known[..., None], truth, np.nan), known, STEP)
    assert np.abs(filled - truth).max() < 1e-5
    # more unknown nodes than the direct solver takes: conjugate gradients
    shape = (24, 24, 24)
    truth = _grid_field(affine, shape).u
    known = np.ones(shape, bool)
    known[3:21, 3:21, 2:22] = False
    assert (~known).sum() > cleaning.DIRECT_SOLVE_LIMIT
    filled = cleaning.inpaint(np.where(known[..., None], truth, np.nan), known, STEP)
    assert np.abs(filled - truth).max() < 1e-3


def _open_shell(shape=(20, 20, 20), radius=7.0):
    """Known nodes inside a cylinder along z; the unknown shell reaches the grid's border."""
    _, y, x = np.indices(shape)
    centre = (shape[1] - 1) / 2
    return (y - centre) ** 2 + (x - centre) ** 2 <= radius**2


def test_a_hole_open_to_the_border_is_solved_directly_up_to_its_own_limit(monkeypatch):
    known = _open_shell()
    unknown = ~known
    assert cleaning.DIRECT_SOLVE_LIMIT < unknown.sum() <= cleaning.OPEN_DIRECT_SOLVE_LIMIT
    assert cleaning.direct_solve_limit(unknown) == cleaning.OPEN_DIRECT_SOLVE_LIMIT
    enclosed = np.ones((24, 24, 24), bool)
    enclosed[3:21, 3:21, 2:22] = False
    assert cleaning.direct_solve_limit(~enclosed) == cleaning.DIRECT_SOLVE_LIMIT
    affine = synthetic.affine(GRADIENT, (30.0, 30.0, 30.0), (1.0, 2.0, 3.0))
    truth = _grid_field(affine, known.shape).u
    values = np.where(known[..., None], truth, np.nan)
    cg_calls = []
    jacobi_cg = cleaning.jacobi_cg
    monkeypatch.setattr(cleaning, "jacobi_cg", lambda *args: cg_calls.append(1) or jacobi_cg(*args))
    direct = cleaning.inpaint(values, known, STEP)
    assert not cg_calls
    assert np.abs(direct - truth).max() < 1e-6
    # the same system by conjugate gradients: one solution within the solver's tolerance
    monkeypatch.setattr(cleaning, "OPEN_DIRECT_SOLVE_LIMIT", cleaning.DIRECT_SOLVE_LIMIT)
    rough = values + np.random.default_rng(5).normal(scale=0.3, size=values.shape)
    iterated = cleaning.inpaint(rough, known, STEP)
    assert cg_calls
    monkeypatch.undo()
    solved = cleaning.inpaint(rough, known, STEP)
    assert np.array_equal(solved[known], rough[known])
    assert np.abs(solved - iterated).max() < 1e-5


def test_columns_at_once_equal_scipy_cg_column_by_column_to_the_bit():
    from scipy import sparse
    from scipy.sparse import linalg as sparse_linalg

    rng = np.random.default_rng(3)
    known = np.ones((16, 16, 16), bool)
    known[2:14, 3:13, 2:15] = False
    values = rng.normal(size=(16, 16, 16, 4))
    matrix, rhs = cleaning._thin_plate_system(values, ~known, STEP)
    normal = (matrix.T @ matrix).tocsc()
    normal_rhs = matrix.T @ rhs
    normal_rhs[:, 2] = 0.0  # a zero right-hand side: returned as it is
    start = rng.normal(size=normal_rhs.shape)
    start[:, 1] = 0.0  # a zero start
    diagonal = normal.diagonal()
    jacobi = sparse_linalg.LinearOperator(normal.shape, matvec=lambda x: x / diagonal)
    for rtol, iterations in ((1e-10, 2000), (1e-6, 2000), (1e-10, 7)):  # converged, early, cut
        expected = np.stack(
            [
                sparse_linalg.cg(
                    normal, normal_rhs[:, c], x0=start[:, c], rtol=rtol, maxiter=iterations,
                    M=jacobi,
                )[0]
                for c in range(4)
            ],
            axis=1,
        )  # fmt: skip
        result = cleaning.jacobi_cg(normal, normal_rhs, start, rtol, iterations)
        assert np.array_equal(result, expected)
    assert isinstance(normal, sparse.csc_matrix)


def test_inpainting_needs_something_known():
    with pytest.raises(ValueError, match="no node"):
        cleaning.inpaint(np.full((3, 3, 3), np.nan), np.zeros((3, 3, 3), bool))


def test_median_test_finds_gross_outliers_and_spares_a_steep_smooth_field():
    rng = np.random.default_rng(2)
    steep = synthetic.shear_band((36.0, 38.0, 40.0), width=6.0, slip=10.0)
    field = _grid_field(steep)
    field.u += rng.normal(0.0, 0.03, field.u.shape)
    clean_residual = cleaning.normalized_median_test(field.u)
    assert np.nanmax(clean_residual) < 2.0  # no false alarm at a peak gradient of 0.8
    bad = rng.random(SHAPE) < 0.05
    kick = rng.normal(0.0, 1.0, (int(bad.sum()), 3))
    kick *= (3.0 + rng.random((len(kick), 1))) / np.linalg.norm(kick, axis=1, keepdims=True)
    field.u[bad] += kick  # every outlier is 3 to 4 voxels off, about one node-to-node jump
    report = cleaning.detect_outliers(field)
    assert np.array_equal(report.median, bad)
    assert report.counts()["median_test"] == int(bad.sum())


def test_clean_replaces_failed_and_outlying_nodes_and_records_provenance():
    rng = np.random.default_rng(3)
    field = _grid_field(SMOOTH)
    truth = field.u.copy()
    field.zncc[:] = 0.95
    outliers = [(3, 3, 3), (8, 9, 10), (12, 2, 7)]
    for node in outliers:
        field.u[node] += (4.0, -3.0, 5.0)
    field.status[5, 5, 5] = Status.DIVERGED
    field.u[5, 5, 5] = np.nan
    field.status[6, 6, 6] = Status.LOW_ZNCC
    field.u[6, 6, 6] = 0.0  # a failed match reported as zero must not stay zero
    field.zncc[9, 9, 9] = 0.3
    field.status[0, :, :] = Status.MASKED
    field.u[0] = np.nan
    field.u += rng.normal(0.0, 0.01, field.u.shape) * np.isfinite(field.u)

    cleaned = cleaning.clean(field, min_zncc=0.5)
    active = np.ones(SHAPE, bool)
    active[0] = False
    assert np.abs(cleaned.u[active] - truth[active]).max() < 0.1
    for node in outliers:
        assert cleaned.status[node] == Status.OUTLIER_REPLACED
        assert cleaned.provenance[node] == Provenance.REPLACED
    assert cleaned.status[5, 5, 5] == Status.DIVERGED  # the reason stays visible
    assert cleaned.provenance[5, 5, 5] == Provenance.REPLACED
    assert cleaned.provenance[9, 9, 9] == Provenance.REPLACED
    assert np.all(cleaned.provenance[0] == Provenance.MASKED)
    assert np.isnan(cleaned.u[0]).all()  # masked nodes are not invented by default
    counts = cleaned.metadata["cleaning"]
    assert counts["median_test"] == 3 and counts["failed"] == 2 and counts["low_zncc"] == 1
    assert cleaned.valid[active].all()
    assert field.provenance.max() == Provenance.MEASURED  # the input is untouched

    filled = cleaning.clean(field, fill_masked=True)
    assert np.all(np.isfinite(filled.u))
    assert np.all(filled.provenance[0] == Provenance.MASKED)
    assert np.abs(filled.u[0] - truth[0]).max() < 0.2


@pytest.mark.parametrize("fill_masked", [False, True])
def test_clean_fills_u_and_the_gradient_in_one_solve_as_in_two(fill_masked):
    rng = np.random.default_rng(4)
    field = _grid_field(SMOOTH)
    field.gradient = rng.normal(0.0, 0.01, (*SHAPE, 3, 3))
    known = _holes()
    field.status[~known] = Status.DIVERGED
    field.u[~known] = np.nan
    field.gradient[~known] = np.nan
    field.status[0] = Status.MASKED
    cleaned = cleaning.clean(field, fill_masked=fill_masked)
    keep = known.copy()
    keep[0] = False
    flat = field.gradient.reshape(*SHAPE, 9)
    u = cleaning.inpaint(field.u, keep, STEP)
    gradient = cleaning.inpaint(flat, keep, STEP)
    if not fill_masked:
        u[0], gradient[0] = field.u[0], flat[0]
    assert np.array_equal(cleaned.u, u, equal_nan=True)
    assert np.array_equal(cleaned.gradient.reshape(*SHAPE, 9), gradient, equal_nan=True)
    assert cleaned.u.flags.c_contiguous and cleaned.gradient.flags.c_contiguous
    # a gradient missing where u is known: filled from its own known nodes
    field.gradient[5, 5, 5] = np.nan
    cleaned = cleaning.clean(field, fill_masked=fill_masked)
    keep_gradient = keep.copy()
    keep_gradient[5, 5, 5] = False
    gradient = cleaning.inpaint(flat, keep_gradient, STEP)
    if not fill_masked:
        gradient[0] = flat[0]
    assert np.array_equal(cleaned.gradient.reshape(*SHAPE, 9), gradient, equal_nan=True)
    assert np.isfinite(cleaned.gradient[5, 5, 5]).all()


def test_clean_of_a_field_with_nothing_usable_fails_loudly():
    field = _grid_field(SMOOTH)
    field.status[:] = Status.DIVERGED
    with pytest.raises(ValueError, match="no node"):
        cleaning.clean(field)


def test_smoothing_lowers_noise_without_moving_a_linear_field_inside():
    rng = np.random.default_rng(4)
    affine = synthetic.affine(GRADIENT, (30.0, 30.0, 30.0))
    field = _grid_field(affine)
    truth = field.u.copy()
    field.u += rng.normal(0.0, 0.2, field.u.shape)
    smoothed = cleaning.clean(field, threshold=1e9, smoothing=1.0)
    inner = (slice(3, -3),) * 3
    before = np.sqrt(np.mean((field.u - truth)[inner] ** 2))
    after = np.sqrt(np.mean((smoothed.u - truth)[inner] ** 2))
    assert after < 0.5 * before
    assert smoothed.metadata["cleaning"]["smoothing"] == 1.0


def test_homogeneous_strain_does_not_eat_the_grid_from_its_borders():
    # 8% strain with a 6-voxel step: half a voxel between nodes, one-sided at the borders
    strain = synthetic.affine(np.diag([-0.08, 0.04, 0.04]), (20.0, 20.0, 20.0), (1.0, 2.0, 3.0))
    field = DisplacementField.zeros((7.0, 7.0, 7.0), (6.0, 6.0, 6.0), (4, 4, 4))
    field.u[:] = synthetic.sample_displacement(strain, field.points.reshape(4, 4, 4, 3))
    assert cleaning.detect_outliers(field).counts()["rejected"] == 0
    assert np.nanmax(cleaning.normalized_median_test(field.u)) < 1e-6
    field.u[1, 2, 1] += (0.0, 3.0, 0.0)
    assert cleaning.detect_outliers(field).median[1, 2, 1]
    assert cleaning.detect_outliers(field).counts()["rejected"] == 1


def test_clean_keeps_measured_uncertainty_and_blanks_it_where_a_value_was_filled_in():
    field = _grid_field(SMOOTH)
    field.zncc[:] = 0.95
    field.uncertainty = np.full((*SHAPE, 3), 0.02)
    field.u[4, 4, 4] += (3.0, 0.0, 0.0)  # an outlier
    field.status[7, 7, 7] = Status.LOW_ZNCC
    cleaned = cleaning.clean(field)
    replaced = cleaned.provenance == Provenance.REPLACED
    assert replaced[4, 4, 4] and replaced[7, 7, 7]
    assert np.all(np.isnan(cleaned.uncertainty[replaced]))
    assert np.all(cleaned.uncertainty[~replaced] == 0.02)
    assert np.all(field.uncertainty == 0.02)  # the input is untouched


def test_cleaning_options_are_one_record_checked_once():
    from napari_dvc_correct.engine.correction.cleaning import CleaningOptions

    options = CleaningOptions(threshold=3.0, fill_masked=True)
    assert options.replace(smoothing=1.0).smoothing == 1.0 and options.smoothing == 0.0
    assert options.as_dict()["threshold"] == 3.0 and options.as_dict()["fill_masked"] is True
    for bad in ({"threshold": 0.0}, {"radius": 0}, {"passes": 0}, {"smoothing": float("nan")}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            CleaningOptions(**bad)
