"""Lazily written output volumes: an earlier file is untouched until the new one is committed."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from napari_dvc_correct.io.atomic import TEMP_MARK
from napari_dvc_correct.io.lazy_outputs import create_output


@pytest.mark.parametrize("name", ["out.tif", "out.zarr"])
def test_earlier_output_survives_until_commit(tmp_path, name):
    final = tmp_path / name
    if final.suffix == ".tif":
        tifffile.imwrite(final, np.ones((2, 4, 4), np.float32), photometric="minisblack")
        before = final.read_bytes()
    output = create_output(final, (2, 4, 4), np.float32)
    assert TEMP_MARK in output.temp.name  # recognisable: a killed run's leftover is cleaned later
    if final.suffix == ".tif":
        assert final.read_bytes() == before  # was replaced by an empty file at creation
    output.write((slice(0, 2),), np.full((2, 4, 4), 7.0, np.float32))
    output.discard()
    assert [p.name for p in tmp_path.iterdir()] == ([name] if final.suffix == ".tif" else [])
    output = create_output(final, (2, 4, 4), np.float32)
    output.write((slice(0, 2),), np.full((2, 4, 4), 7.0, np.float32))
    output.commit()
    assert [p.name for p in tmp_path.iterdir()] == [name]
