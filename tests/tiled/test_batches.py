"""A tiled batch's two tasks (tiled/batches.py): matched, then judged at the whole run's noise."""

import numpy as np

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.tiled import batches, correlate_tiled

PARAMS = CorrelationParams(subvolume=15, step=8, tolerance=1e-5)


def _counted_reads(monkeypatch):
    reads = []
    real = batches.read_regions

    def counted(job, *volumes):
        reads.append(tuple(job.core_index[:1]))
        return real(job, *volumes)

    monkeypatch.setattr(batches, "read_regions", counted)
    return reads


def test_a_clean_batch_is_read_once(monkeypatch):
    """Noise-free and nothing to repair: the judge needs no volume, so each batch's region is
    read by its first task only."""
    reference = synthetic.textured_volume((48, 48, 48), 2.0, seed=5)
    deformed = synthetic.deform_volume(reference, synthetic.translation((0.4, -0.3, 0.7)))
    reads = _counted_reads(monkeypatch)
    field = correlate_tiled(reference, deformed, PARAMS, batch_shape=(2, 2, 4))
    assert field.metadata["tiled"]["batches"] == 4
    assert np.all(field.status == Status.CONVERGED)
    assert len(reads) == 4 and len(set(reads)) == 4


def test_a_noisy_batch_is_read_again_to_measure_its_uncertainty(monkeypatch):
    """On noisy scans the judge measures each match's sensitivity from the deformed scan: the
    second task reads its region again (once)."""
    truth = synthetic.translation((0.4, -0.3, 0.7))
    reference, deformed, _ = synthetic.noisy_ct_pair((48, 48, 48), truth, noise=0.05, seed=5)
    reads = _counted_reads(monkeypatch)
    field = correlate_tiled(reference, deformed, PARAMS, batch_shape=(2, 2, 4))
    assert field.metadata["tiled"]["batches"] == 4
    assert len(reads) == 8 and all(reads.count(r) == 2 for r in reads)
    assert field.metadata["timings"]["task_s"]["judge_prefilter_s"] > 0
