"""The Export panel without Qt: what a request writes, and what it refuses before writing."""

from __future__ import annotations

import numpy as np
import pytest


def test_points_refuse_what_needs_a_grid(tmp_path):
    """The model refuses grid formats and grid extras for a result at points, writing nothing."""
    from napari_dvc_correct.engine.fields.scattered import ScatteredField
    from napari_dvc_correct.widgets import export_model as model

    points = ScatteredField(points=np.array([[10.0, 11.0, 12.5]]), u=np.array([[0.1, 0.2, 0.3]]))
    cases = {
        "x.vti": ({}, "no grid for .vti"),
        "x.h5": ({}, "no grid for .h5"),
        "x.csv": ({"strain_tiff": True}, "needs a grid field"),
        "y.csv": ({"report": {"title": "r"}}, "come from Evaluate"),
    }
    for name, (options, message) in cases.items():
        request = model.ExportRequest(field=points, path=tmp_path / name, **options)
        with pytest.raises(ValueError, match=message):
            list(model.run_export(request))
    assert list(tmp_path.iterdir()) == []


def test_an_export_never_writes_over_a_file_a_layer_was_opened_from(tmp_path):
    from napari_dvc_correct.widgets.export_model import check_not_open

    scans = tmp_path / "rock.npz"
    scans.write_bytes(b"scans")
    stack = tmp_path / "dvc_uz.tif"
    stack.write_bytes(b"a scan")
    with pytest.raises(ValueError, match="rock.npz, the file of an open layer"):
        check_not_open(tmp_path / "rock.npz", [None, str(scans)])
    with pytest.raises(ValueError, match="dvc_uz.tif, the file of an open layer"):
        check_not_open(tmp_path / "dvc.tif", [str(stack)])  # writes dvc_uz.tif
    check_not_open(tmp_path / "field.npz", [str(scans), str(stack), None])
    check_not_open(tmp_path / "rock.h5", [str(scans)])


@pytest.mark.skipif(not __import__("os").path.isdir("/proc/self"), reason="needs Linux /proc")
def test_a_folder_that_takes_no_files_is_refused_in_words():
    # the panel tried, and said "[Errno 2] No such file or directory: '/proc/.x.h5.ndc-tmp-...'"
    from napari_dvc_correct.widgets.export_model import check_path

    with pytest.raises(ValueError, match=r"cannot write into /proc"):
        check_path("/proc/x.h5", ".h5")
