"""The whole-volume pass of tiled correlation, block by block, against the whole volume's numbers."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.io.lazy import ArrayVolume
from napari_dvc_correct.tiled import whole_volume


def test_whole_volume_pass_equals_the_whole_volume_quantities(monkeypatch):
    import dask

    from napari_dvc_correct.engine.correlation.initial_guess import bin_volume, global_shift

    reference = synthetic.textured_volume((101, 50, 199), 3.0, seed=2)  # binned by 3, cropped
    deformed = np.roll(reference, (7, -4, 11), axis=(0, 1, 2))
    mask = np.zeros(reference.shape, bool)
    mask[10:90, 5:45, 30:150] = True
    monkeypatch.setattr(whole_volume, "SHIFT_BLOCK_VOXELS", 20_000)  # many blocks
    for m in (None, mask):
        volumes = [None if v is None else ArrayVolume(v) for v in (reference, deformed, m)]
        tasks, factor = whole_volume.volume_tasks(*volumes, levels=2)
        assert factor == 3 and len(tasks) > 5
        results = dask.compute(*tasks, scheduler="sync")
        whole = whole_volume.combine(results, reference.shape, factor, levels=2)
        np.testing.assert_array_equal(whole.shift, global_shift(reference, deformed))
        for f in (1, 2, 4):
            binned = bin_volume(reference, f)
            if m is not None:
                binned = binned[(bin_volume(m.astype(np.float32), f) >= 0.5) if f > 1 else m]
            assert whole.texture_std[f] == pytest.approx(float(np.std(binned)), rel=1e-5)
    assert np.all(np.abs(whole.shift - (7, -4, 11)) <= factor)
