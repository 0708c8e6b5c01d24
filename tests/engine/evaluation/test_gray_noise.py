"""Each scan's noise for the gray-level map's fit (engine/evaluation/gray_noise.py): a scan's white
noise is read from its finest differences, and the pull-back's interpolation keeps a known share
of it."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample
from napari_dvc_correct.engine.evaluation.gray_noise import (
    PairNoise,
    interpolation_gain,
    noise_box,
    pair_noise,
    scan_noise_variance,
    scan_noises,
)


@pytest.mark.parametrize(
    "pattern",
    [
        lambda s: synthetic.concrete_ct_volume(s, seed=8),
        lambda s: synthetic.textured_volume(s, 2.0, seed=5),
    ],
)
@pytest.mark.parametrize("fraction", [0.02, 0.05])
def test_the_noise_of_a_textured_scan_is_measured(pattern, fraction):
    texture = pattern((48, 48, 48))
    sigma = synthetic.ct_noise_sigma(texture, fraction)
    noisy = synthetic.add_noise(texture, sigma, seed=3)
    assert scan_noise_variance(noisy) == pytest.approx(sigma**2, rel=0.1)
    # the smooth texture alone reads as almost no noise
    assert scan_noise_variance(texture) < 0.05 * sigma**2


def test_a_scan_of_integer_gray_levels_is_not_rounded_to_its_quantum():
    texture = synthetic.textured_volume((48, 48, 48), 2.0, seed=5)
    texture = 100.0 + 10.0 * (texture - texture.mean()) / texture.std()
    for sigma in (0.7, 1.6):
        scan = np.round(synthetic.add_noise(texture, sigma, seed=4)).astype(np.uint8)
        # rounding adds 1/12 gray level² of its own noise
        assert scan_noise_variance(scan) == pytest.approx(sigma**2 + 1 / 12, rel=0.1)


def test_the_pull_back_keeps_the_interpolations_share_of_the_noise():
    noise = np.random.default_rng(0).standard_normal((40, 40, 40)).astype(np.float32)
    coefficients = prefilter(noise)
    grid = np.stack(np.meshgrid(*(np.arange(10, 30),) * 3, indexing="ij"), -1).reshape(-1, 3)
    for shift in [(0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (0.4, -1.3, 0.25), (0.5, 0.5, 0.5)]:
        moved = sample(coefficients, grid + np.asarray(shift))
        gain = interpolation_gain(np.tile(shift, (7, 1)))
        assert float(np.var(moved)) == pytest.approx(gain, rel=0.05)
    assert interpolation_gain(np.zeros((3, 3))) == pytest.approx(1.0)
    assert interpolation_gain(np.full((2, 3), 0.5)) == pytest.approx(0.756**3, rel=0.01)
    assert interpolation_gain(np.full((2, 3), np.nan)) == 1.0  # nothing known: all of it


def test_a_pair_of_scans_and_a_field_give_the_noise_of_g_and_of_the_moved_scan():
    texture = synthetic.textured_volume((80, 80, 80), 2.0, seed=5)
    g = synthetic.add_noise(texture, 0.02, seed=1)
    f = synthetic.add_noise(0.5 * texture, 0.03, seed=2)
    box = noise_box(g.shape)
    assert box == (slice(8, 72),) * 3
    assert noise_box((20, 100, 64)) == (slice(0, 20), slice(18, 82), slice(0, 64))
    reads = []

    def read(volume, region):
        reads.append(region)
        return volume[region]

    noises = scan_noises(g, f, read=read)
    assert reads == [box, box] and noises == scan_noises(g, f)
    assert noises[0] == pytest.approx(0.02**2, rel=0.1)
    assert noises[1] == pytest.approx(0.03**2, rel=0.1)
    pair = pair_noise(*noises, np.tile([0.5, 0.0, 0.0], (5, 1)))
    assert pair.reference == noises[0]
    assert pair.moved == pytest.approx(noises[1] * 0.756, rel=0.01)
    assert pair.ratio == pytest.approx(pair.reference / pair.moved)
    assert PairNoise.from_dict(pair.to_dict()) == pair and PairNoise.from_dict(None) is None
    assert pair_noise(np.nan, 1.0, np.zeros((1, 3))) is None
    assert scan_noise_variance(np.zeros((1, 5, 5))) == 0.0
