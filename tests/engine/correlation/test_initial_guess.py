"""Integer initial guesses: block-mean binning, the pyramid depth, the rigid shift, the FFT search.

Shifted volumes are made with ``np.roll`` (integer shifts of a periodic texture: exact) or a Fourier
shift (sub-voxel, exact for a periodic band-limited texture), never with the engine's own B-spline.
Convention everywhere: ``F(X + t) = G(X)``, i.e. ``F`` is ``G`` moved by ``+t``.
"""

import warnings

import numpy as np
import pytest
from scipy import ndimage

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.initial_guess import (
    bin_volume,
    fft_search,
    global_shift,
    pyramid_levels,
)

SHAPE = (48, 48, 48)


@pytest.fixture(scope="module")
def texture():
    # periodic (smoothed with mode="wrap"), so np.roll and Fourier shifts move it exactly
    return synthetic.textured_volume(SHAPE, 2.0, seed=1)


def _roll(volume, shift):
    return np.roll(volume, shift, axis=(0, 1, 2))


def _fourier_shift(volume, shift):
    return np.fft.ifftn(ndimage.fourier_shift(np.fft.fftn(volume), shift)).real


# --- bin_volume --------------------------------------------------------------------------------
@pytest.mark.parametrize("factor", [2, 3])
def test_bin_volume_is_the_block_mean_and_crops_to_whole_blocks(factor):
    volume = np.random.default_rng(0).integers(0, 60000, (9, 10, 11)).astype(np.uint16)
    binned = bin_volume(volume, factor)
    expected_shape = (9 // factor, 10 // factor, 11 // factor)
    assert binned.shape == expected_shape
    assert binned.dtype == np.float32
    for index in np.ndindex(expected_shape):
        block = volume[tuple(slice(factor * i, factor * i + factor) for i in index)]
        assert binned[index] == pytest.approx(block.astype(np.float64).mean(), rel=1e-6)


def test_bin_volume_by_one_is_a_float32_copy_and_too_small_volumes_are_refused():
    volume = np.arange(24, dtype=np.int32).reshape(2, 3, 4)
    same = bin_volume(volume, 1)
    assert same.dtype == np.float32
    np.testing.assert_array_equal(same, volume)
    with pytest.raises(ValueError, match="too small to bin by 3"):
        bin_volume(volume, 3)


# --- pyramid_levels ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("radius", "subvolume", "shape", "levels"),
    [
        (4, 31, (256,) * 3, 0),  # already within the coarse radius
        (8, 31, (256,) * 3, 1),  # ceil(8 / 2) = 4
        (9, 41, (256,) * 3, 2),  # ceil(9 / 2) = 5 > 4, ceil(9 / 4) = 3
        (9, 31, (256,) * 3, 1),  # the same, but 31 // 4 = 7 < 9 voxels stops the second level
        (40, 41, (256,) * 3, 2),  # a third level would leave a 41 // 8 = 5 voxel subvolume
        (40, 141, (40, 400, 400), 1),  # a second level would leave 40 // 4 = 10 < 16 voxels
        (100, 21, (512,) * 3, 1),  # 21 // 4 = 5 < 9: stops even though ceil(100 / 2) > 4
    ],
)
def test_pyramid_levels_for_small_and_large_search_radii(radius, subvolume, shape, levels):
    assert pyramid_levels(radius, subvolume, shape) == levels


def test_pyramid_levels_grows_with_the_radius():
    depths = [pyramid_levels(r, 301, (1000,) * 3) for r in (2, 8, 16, 32, 64)]
    assert depths == [0, 1, 2, 3, 4]


# --- global_shift ------------------------------------------------------------------------------
@pytest.mark.parametrize("shift", [(5, -3, 7), (0, 0, 0), (-6, 2, -1)])
def test_global_shift_recovers_a_small_integer_shift_exactly(texture, shift):
    found = global_shift(texture, _roll(texture, shift))
    np.testing.assert_array_equal(found, shift)
    assert found.dtype == np.int64
    # swapping the volumes reverses the shift
    np.testing.assert_array_equal(global_shift(_roll(texture, shift), texture), -np.array(shift))


def test_global_shift_of_a_non_cubic_volume():
    volume = synthetic.textured_volume((32, 48, 40), 2.0, seed=2)
    shift = (-5, 6, 3)
    np.testing.assert_array_equal(global_shift(volume, _roll(volume, shift)), shift)


def test_global_shift_of_a_non_periodic_crop():
    # F and G are two windows of a larger specimen (material enters and leaves at the faces)
    big = synthetic.textured_volume((64, 64, 64), 2.0, seed=4)
    shift = np.array([4, -5, 3])
    low = np.array([8, 8, 8])
    reference = big[8:56, 8:56, 8:56]
    s = low - shift
    deformed = big[s[0] : s[0] + 48, s[1] : s[1] + 48, s[2] : s[2] + 48]
    np.testing.assert_array_equal(global_shift(reference, deformed), shift)


def test_global_shift_of_large_and_binned_shifts_is_within_the_binning_factor(texture):
    # the documented accuracy: about the binning factor (the Hann window pulls large shifts
    # toward zero by up to one voxel); the per-POI search refines it
    shift = np.array([15, -12, 2])
    deformed = _roll(texture, shift)
    assert np.abs(global_shift(texture, deformed) - shift).max() <= 1
    for max_size, factor in ((24, 2), (16, 3)):
        found = global_shift(texture, deformed, max_size=max_size)
        assert np.abs(found - shift).max() <= factor
        assert np.all(found % factor == 0)  # a binned estimate is a multiple of the factor


def test_global_shift_of_a_sub_voxel_shift_is_within_one_voxel(texture):
    shift = np.array([2.3, -3.6, 1.2])
    found = global_shift(texture, _fourier_shift(texture, shift))
    assert np.abs(found - shift).max() < 1.0
    # the same with an independent interpolator (scipy's cubic spline, periodic)
    moved = ndimage.shift(texture, shift, order=3, mode="grid-wrap")
    assert np.abs(global_shift(texture, moved) - shift).max() < 1.0


# --- fft_search --------------------------------------------------------------------------------
# subvolumes (half 7) whose displaced copy stays inside the volume; (8, 24, 24) reads a region
# that sticks out of the volume (padded with the mean gray value of its part inside)
CENTERS = np.array([[16, 16, 16], [24, 24, 24], [30, 20, 26], [8, 24, 24], [20, 34, 12]])


def test_fft_search_finds_an_integer_shift_at_every_poi(texture):
    shift = np.array([3, -2, 4])
    displacement, peak = fft_search(
        texture, _roll(texture, shift), CENTERS, 7, np.zeros((len(CENTERS), 3)), 5
    )
    np.testing.assert_array_equal(np.rint(displacement), np.tile(shift, (len(CENTERS), 1)))
    # the parabolic sub-voxel correction of an exact integer match is small
    assert np.abs(displacement - shift).max() < 0.1
    np.testing.assert_allclose(peak, 1.0, atol=1e-6)


def test_fft_search_searches_around_the_guesses(texture):
    shift = np.array([9, -8, 10])
    deformed = _roll(texture, shift)
    centers = CENTERS[:3]
    guesses = np.tile([8.2, -7.4, 9.0], (3, 1))  # rounded to (8, -7, 9): within radius 2
    displacement, peak = fft_search(texture, deformed, centers, 7, guesses, 2)
    np.testing.assert_array_equal(np.rint(displacement), np.tile(shift, (3, 1)))
    np.testing.assert_allclose(peak, 1.0, atol=1e-6)
    # from zero with the same radius the shift is out of reach: the answer stays within the
    # radius and is a poor match
    displacement, peak = fft_search(texture, deformed, centers, 7, np.zeros((3, 3)), 2)
    assert np.abs(displacement).max() <= 2.5
    assert np.all(peak < 0.8)


def test_fft_search_sub_voxel_peak(texture):
    shift = np.array([2.3, -1.6, 0.4])
    deformed = _fourier_shift(texture, shift)
    displacement, peak = fft_search(texture, deformed, CENTERS, 7, np.zeros((len(CENTERS), 3)), 4)
    # a parabola through three ZNCC samples: a quarter voxel at worst, far better than rounding
    assert np.abs(displacement - shift).max() < 0.25
    assert np.sqrt(np.mean((displacement - shift) ** 2)) < 0.12
    assert np.all(peak > 0.95)


def test_fft_search_batches_give_the_same_answer(texture):
    deformed = _roll(texture, (1, 2, -3))
    guesses = np.zeros((len(CENTERS), 3))
    one_batch = fft_search(texture, deformed, CENTERS, 7, guesses, 4)
    one_by_one = fft_search(texture, deformed, CENTERS, 7, guesses, 4, batch_bytes=1)
    np.testing.assert_allclose(one_by_one[0], one_batch[0], atol=1e-9)
    np.testing.assert_allclose(one_by_one[1], one_batch[1], atol=1e-9)


def test_fft_search_flat_subvolume_has_nan_peak_and_keeps_its_guess(texture):
    reference = texture.copy()
    reference[9:24, 9:24, 9:24] = 0.5  # the subvolume around (16, 16, 16) is flat
    deformed = _roll(reference, (2, 0, 0))
    guesses = np.array([[1.0, 1.0, -2.0], [0.0, 0.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a flat subvolume is an answer (NaN), not a warning
        displacement, peak = fft_search(reference, deformed, CENTERS[[0, 2]], 7, guesses, 3)
    assert np.isnan(peak[0])
    np.testing.assert_array_equal(displacement[0], guesses[0])
    # its neighbour in the same batch is unaffected
    np.testing.assert_array_equal(np.rint(displacement[1]), [2, 0, 0])
    assert peak[1] == pytest.approx(1.0, abs=1e-6)


def test_fft_search_at_the_border_reads_only_near_its_window(texture):
    """The part of a search window beyond the volume is filled from the window itself.

    So a region of the volume (a tiled batch, which pads the window with the same local value)
    gives the same answer as the whole volume: here a POI at the low z border, whose window
    sticks out of the volume, searched in the whole volume and in a crop far from its other
    sides, one of them darker overall (a fill taken over the whole volume would differ).
    """
    deformed = _roll(texture, (-3, 2, 1))
    deformed[:, :, 30:] -= 0.4  # far from the POI: changes the whole volume's mean only
    center = np.array([[8, 20, 14]])  # half 7, radius 5: z window from -4, beyond the volume
    guesses = np.zeros((1, 3))
    whole = fft_search(texture, deformed, center, 7, guesses, 5)
    crop = (slice(0, 30), slice(4, 40), slice(0, 30))
    region = fft_search(texture[crop], deformed[crop], center - [0, 4, 0], 7, guesses, 5)
    np.testing.assert_allclose(region[0], whole[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(region[1], whole[1], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.rint(whole[0]), [[-3, 2, 1]])
