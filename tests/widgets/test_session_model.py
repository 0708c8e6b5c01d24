"""Session files are checked, not trusted (issue 27 item 8): a hand-edited or foreign session is
one ValueError, a newer version is refused, and no field file is read or written outside the
session's folder. Qt-free (:mod:`napari_dvc_correct.widgets.session_model`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.widgets.session_model import FORMAT, read_session, write_session


def _scan(tmp_path) -> dict:
    np.save(tmp_path / "ref.npy", np.zeros((4, 4, 4), np.float32))
    return {"name": "ref", "path": str(tmp_path / "ref.npy"), "scale": [1.0, 1.0, 1.0],
            "translate": [0.0, 0.0, 0.0], "units": None}  # fmt: skip


def _content(tmp_path, **changes) -> dict:
    content = {"format": FORMAT, "version": 1, "scans": [_scan(tmp_path)], "panels": {},
               "fields": {}}  # fmt: skip
    content.update(changes)
    return content


def _nested(depth: int) -> str:
    return "[" * depth + "]" * depth


BAD = {
    "version 999": ({"version": 999}, "newer than this napari-dvc-correct reads"),
    "version text": ({"version": "1"}, "invalid session version"),
    "scans not a list": ({"scans": {"a": 1}}, "'scans' must be a list"),
    "scan without path": ({"scans": [{"name": "a"}]}, "needs a 'name' and a 'path'"),
    "scale text": ({"scans": "SCALE"}, "'scans' must be a list"),
    "panels a list": ({"panels": ["Correlate"]}, "'panels' must map"),
    "panel settings text": ({"panels": {"Correlate": "fast"}}, "'panels' must map"),
    "fields a list": ({"fields": ["a.npz"]}, "'fields' must map"),
    "field outside": ({"fields": {"a": "../../etc/passwd"}}, "points outside the session"),
    "field absolute": ({"fields": {"a": "/etc/passwd"}}, "points outside the session"),
    "no fields key": ({"fields": None}, "'fields' must map"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_hand_edited_sessions_are_one_value_error(tmp_path, case):
    changes, message = BAD[case]
    content = _content(tmp_path, **changes)
    if case == "scale text":
        content["scans"] = "SCALE"
    path = tmp_path / "s.dvc-session.json"
    path.write_text(json.dumps(content))
    with pytest.raises(ValueError, match=message):
        read_session(path)


def test_bad_scan_placement_and_deep_nesting_are_value_errors(tmp_path):
    path = tmp_path / "s.dvc-session.json"
    scan = _scan(tmp_path)
    for key, value in (("scale", "big"), ("scale", [0.0, 1.0, 1.0]), ("translate", [1e400] * 3)):
        path.write_text(json.dumps(_content(tmp_path, scans=[{**scan, key: value}])))
        with pytest.raises(ValueError, match=f"'{scan['name']}'"):
            read_session(path)
    path.write_text(f'{{"format": "{FORMAT}", "version": 1, "scans": {_nested(100000)}}}')
    with pytest.raises(ValueError, match="not a readable session file"):
        read_session(path)


def test_a_field_source_never_writes_outside_the_session_folder(tmp_path):
    field = DisplacementField.zeros((4.0,) * 3, (4.0,) * 3, (2, 2, 2))
    session = tmp_path / "deep" / "run"
    session.parent.mkdir()
    fields = {"../../x": field, "x": field, ".hidden/../y": field}
    written = write_session(session, [_scan(tmp_path)], {}, fields)
    outside = sorted(p.name for p in tmp_path.iterdir())
    assert outside == ["deep", "ref.npy"], outside
    content = read_session(written)
    assert set(content["fields"]) == set(fields)
    files = [content["fields"][source] for source in fields]
    assert len(set(files)) == 3  # distinct files for distinct sources
    assert all(f.startswith(str(session.parent.resolve())) for f in files)
