"""Synthetic volumes and fields: the displacement functions and the deformation they make."""

import numpy as np

from napari_dvc_correct.engine import synthetic


def test_displacement_functions_are_what_they_say():
    points = np.array([[0.0, 0.0, 0.0], [10.0, 20.0, 30.0]])
    np.testing.assert_array_equal(synthetic.translation((1, -2, 3))(points), [[1, -2, 3]] * 2)
    gradient = np.array([[0.01, 0.0, 0.02], [0.0, -0.01, 0.0], [0.0, 0.0, 0.03]])
    u = synthetic.affine(gradient, center=(10.0, 20.0, 30.0), shift=(0.5, 0.0, 0.0))(points)
    np.testing.assert_allclose(u[1], [0.5, 0.0, 0.0])  # the centre moves by the shift
    np.testing.assert_allclose(u[0], [0.5 - 0.1 - 0.6, 0.2, -0.9])
    np.testing.assert_allclose(synthetic.sample_displacement(synthetic.translation((1, 2, 3)),
                                                             points), [[1, 2, 3]] * 2)  # fmt: skip


def test_an_integer_translation_deforms_by_a_roll():
    """``F(X + u) = G(X)``: a shift of whole voxels moves every interior voxel by it."""
    reference = synthetic.textured_volume((20, 22, 24), feature_size=2.0, seed=1)
    assert reference.shape == (20, 22, 24) and np.isfinite(reference).all()
    deformed = synthetic.deform_volume(reference, synthetic.translation((2.0, -1.0, 3.0)))
    inner = (slice(4, 16), slice(4, 18), slice(4, 20))
    rolled = np.roll(reference, (2, -1, 3), axis=(0, 1, 2))
    np.testing.assert_allclose(deformed[inner], rolled[inner], atol=1e-4)


def test_noise_is_reproducible_and_of_the_asked_size():
    volume = np.zeros((32, 32, 32), np.float32)
    a = synthetic.add_noise(volume, 3.0, seed=5)
    np.testing.assert_array_equal(a, synthetic.add_noise(volume, 3.0, seed=5))
    assert abs(float(np.std(a)) - 3.0) < 0.05
