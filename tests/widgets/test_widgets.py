"""The panels are imported only when asked for, by the names napari's manifest uses."""

import subprocess
import sys

import pytest

from napari_dvc_correct import widgets


def test_each_panel_name_gives_its_module_s_class():
    from napari_dvc_correct.widgets import correct, correlate, evaluate, export, view

    modules = {"CorrectWidget": correct, "CorrelateWidget": correlate, "EvaluateWidget": evaluate,
               "ExportWidget": export, "ViewWidget": view}  # fmt: skip
    assert sorted(widgets.__all__) == sorted(modules)
    for name, module in modules.items():
        assert getattr(widgets, name) is getattr(module, name)
    with pytest.raises(AttributeError, match="no attribute 'SideWidget'"):
        widgets.SideWidget  # noqa: B018


def test_importing_the_package_loads_no_panel():
    code = (
        "import sys, napari_dvc_correct.widgets as w; "
        "print(any(m.startswith('napari_dvc_correct.widgets.') for m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.stdout.strip() == "False", done.stderr
