"""A field from another tool, corrected by our strategy: spam TSV of a first-order shear band.

The field is made with a first-order method (our own correlate, first-order shape function) on a
synthetic shear-band pair, written as a ``spam-ldic`` TSV (spam's columns, z, y, x, Phi = I + du/dX),
read back as any spam user's file would be, corrected, and compared with the known truth.
"""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction.self_correction import correct
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.io.formats import read_field, read_points, write_field

SIZE = 56
BAND = synthetic.shear_band((SIZE / 2,) * 3, width=6.0, slip=9.0, shift=(3.0, -2.0, 4.0))
PARAMS = CorrelationParams(subvolume=21, step=5, order=1)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.two_phase_volume(s, seed=4), (SIZE,) * 3, BAND, margin=20
    )
    reference = synthetic.add_noise(reference, 4.0, seed=1)
    deformed = synthetic.add_noise(deformed, 4.0, seed=2)
    measured = correlate(reference, deformed, PARAMS)
    path = tmp_path_factory.mktemp("spam") / "ldic.tsv"
    write_field(measured, path, "spam")
    return reference, deformed, measured, path


def rmse(field):
    """RMS error against the truth (voxels), usable fraction, fraction off by over a voxel."""
    error = np.linalg.norm(field.displacement - BAND(field.points), axis=1)
    usable = np.isfinite(error)
    rms = float(np.sqrt(np.mean(error[usable] ** 2)))
    return rms, float(usable.mean()), float(np.mean(error[usable] > 1.0))


def test_the_spam_file_is_spams_layout_of_the_measured_field(case):
    _, _, measured, path = case
    header = path.read_text().splitlines()[0].split("\t")
    assert (
        header[:20]
        == (
            "NodeNumber Zpos Ypos Xpos Fzz Fzy Fzx Zdisp Fyz Fyy Fyx Ydisp Fxz Fxy Fxx Xdisp "
            "error iterations returnStatus deltaPhiNorm"
        ).split()
    )
    imported = read_field(path)
    assert imported.same_grid(measured)
    np.testing.assert_allclose(imported.u, measured.u, atol=1e-6, equal_nan=True)


def test_correcting_an_imported_spam_field_lowers_its_error(case):
    reference, deformed, _, path = case
    imported = read_field(path)
    assert imported.params == {}  # spam files do not say which subvolume was used
    corrected = correct(reference, deformed, imported, PARAMS, max_passes=2)
    before, usable_before, off_before = rmse(imported)
    after, usable_after, off_after = rmse(corrected)
    # measured on the 2-vCPU machine: RMSE 0.63 -> 0.43 voxel, nodes off by > 1 voxel 9.3% -> 1.7%
    assert usable_before > 0.9 and usable_after >= usable_before
    assert after < 0.8 * before, (before, after)
    assert off_before > 0.03 and off_after < 0.5 * off_before, (off_before, off_after)
    # ... and goes back to spam, at the same nodes
    out = path.with_name("corrected.tsv")
    write_field(corrected, out, "spam")
    back = read_points(out)
    np.testing.assert_allclose(back.points, corrected.points, atol=1e-6)
