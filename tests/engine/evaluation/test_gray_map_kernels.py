"""The local gray-level map applied in one compiled pass equals the NumPy blend to the bit."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.gray_levels import GrayLevelMap
from napari_dvc_correct.engine.evaluation.gray_map_kernels import apply_local_map


def _map(shape, cell, seed):
    rng = np.random.default_rng(seed)
    cells = tuple(max(1, int(np.ceil(n / cell))) for n in shape)
    return GrayLevelMap(
        contrast=1.1,
        offset=-3.0,
        cell=cell,
        local_contrast=rng.uniform(0.8, 1.3, cells),
        local_offset=rng.normal(0.0, 20.0, cells),
        volume_shape=shape,
    )


def _numpy_apply(gray: GrayLevelMap, moved, region):
    """The map as NumPy computes it: coefficients blended whole, then ``a · F + b`` (float32)."""
    a, b = gray.coefficients(region)
    return a * moved + b


@pytest.mark.parametrize(
    ("shape", "cell", "region"),
    [
        ((40, 33, 29), 8, None),  # the whole volume
        ((40, 33, 29), 8, (slice(5, 31), slice(0, 33), slice(7, 20))),  # a block
        ((17, 50, 9), 16, None),  # a single cell along x: no blend there
        ((64, 64, 64), 12, (slice(60, 64), slice(1, 2), slice(0, 64))),  # the clipped edge
    ],
)
def test_applied_map_equals_numpy_bit_for_bit(shape, cell, region):
    gray = _map(shape, cell, seed=cell)
    region = tuple(slice(0, n) for n in shape) if region is None else region
    rng = np.random.default_rng(1)
    moved = rng.normal(100.0, 30.0, tuple(s.stop - s.start for s in region)).astype(np.float32)
    moved.flat[::97] = np.nan  # undefined voxels stay undefined
    expected = _numpy_apply(gray, moved, region)
    result = gray.apply(moved, region)
    assert result.dtype == np.float32
    assert np.array_equal(result, expected, equal_nan=True)
    assert np.isnan(result.flat[::97]).all()
    assert np.array_equal(
        apply_local_map(gray.local_contrast, gray.local_offset, cell, moved, region),
        expected,
        equal_nan=True,
    )


def test_a_block_of_another_shape_is_refused():
    gray = _map((20, 20, 20), 8, seed=0)
    with pytest.raises(ValueError, match="does not match"):
        apply_local_map(
            gray.local_contrast, gray.local_offset, 8, np.zeros((4, 4, 4), np.float32),
            (slice(0, 5), slice(0, 4), slice(0, 4)),
        )  # fmt: skip


def _numpy_block_sums(reference, moved, region, volume_shape, cell, previous):
    """The per-cell sums as NumPy computed them: float64 copies, a keep mask, six bincounts."""
    from napari_dvc_correct.engine.evaluation.gray_levels import TRIM_RMS, cells_shape

    g = np.asarray(reference, dtype=np.float64)
    f = np.asarray(moved, dtype=np.float64)
    keep = np.isfinite(f) & np.isfinite(g)
    if previous is not None:
        keep &= np.abs(previous.apply(moved, region) - g) <= TRIM_RMS * previous.rms
    shape = cells_shape(volume_shape, cell)
    parts = [
        np.minimum(np.arange(s.start, s.stop) // cell if cell else np.zeros(s.stop - s.start, int),
                   shape[axis] - 1)
        for axis, s in enumerate(region)
    ]  # fmt: skip
    index = (parts[0][:, None, None] * (shape[1] * shape[2]) + parts[1][None, :, None] * shape[2]
             + parts[2][None, None, :])[keep]  # fmt: skip
    size = int(np.prod(shape))
    f, g = f[keep], g[keep]
    counts = np.bincount(index, minlength=size).astype(np.float64).reshape(shape)
    weighted = [np.bincount(index, weights=v, minlength=size).reshape(shape)
                for v in (f, g, f * f, f * g, g * g)]  # fmt: skip
    return [counts, *weighted]


@pytest.mark.parametrize("trim", ["none", "global", "local"])
@pytest.mark.parametrize(
    ("cell", "region"),
    [(8, (slice(0, 40), slice(0, 33), slice(0, 29))), (8, (slice(16, 27), slice(3, 30), slice(0, 29))),
     (0, (slice(0, 40), slice(0, 33), slice(0, 29)))],
)  # fmt: skip
def test_cell_sums_equal_numpy_bit_for_bit(trim, cell, region):
    from napari_dvc_correct.engine.evaluation.gray_levels import block_sums

    volume_shape = (40, 33, 29)
    rng = np.random.default_rng(5)
    block = tuple(s.stop - s.start for s in region)
    reference = rng.integers(0, 4000, block).astype(np.uint16)  # integers, as scans are read
    moved = (reference * 0.9 + rng.normal(0.0, 300.0, block)).astype(np.float32)
    moved.flat[::53] = np.nan
    moved.flat[7::211] = 1e5  # voxels the trimmed fit leaves out
    previous = {
        "none": None,
        "global": GrayLevelMap(contrast=1.1, offset=5.0, rms=250.0),
        "local": _map(volume_shape, 8, seed=2),
    }[trim]
    if previous is not None and previous.is_local:
        previous = GrayLevelMap(**{**previous.__dict__, "rms": 800.0})
    expected = _numpy_block_sums(reference, moved, region, volume_shape, cell, previous)
    sums = block_sums(reference, moved, region, volume_shape, cell, previous)
    for name, value in zip(("n", "f", "g", "ff", "fg", "gg"), expected, strict=True):
        assert np.array_equal(getattr(sums, name), value), name
    assert sums.n.sum() < reference.size  # some voxels were left out
