"""Main-thread CPU of each step of showing a field (``viewer_layers.show_field_steps``) and of
the event processing (the draw) after it, in a shown viewer: what one turn of the event loop
costs when a result comes.

The fields are synthetic (13³ nodes as on the 96³ pair at step 6; a 4-state series of 8³ nodes
as on the 64³ series) over a 96³ scan: a first field, a second one (new layers beside it), the
second again (its layers updated in place) and a series (4-D layers). CPU seconds of the main
thread (``time.thread_time``), so the machine's load stretches them little; the wall time
beside them. ``--at-once`` runs each field's steps back to back, then processes events once;
code without the steps (before branch uigaps) shows each field at once (``show_field``): the
turn the panels had before (drawing by Mesa's llvmpipe threads is not in the CPU).

    xvfb-run -a -s "-screen 0 1600x1000x24" python benchmarks/bench_show_steps.py [--at-once]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _field(shape, seed):
    import numpy as np

    from napari_dvc_correct.engine.fields.field import DisplacementField

    u = np.random.default_rng(seed).normal(0, 1.0, (*shape, 3))
    return DisplacementField(origin=(10.0,) * 3, step=(6.0,) * 3, u=u)


def _steps(V, viewer, tuples):
    """The steps of showing ``tuples``; one step where the code has no steps (old code)."""
    if hasattr(V, "show_field_steps"):
        return V.show_field_steps(viewer, tuples)

    def at_once():
        V.show_field(viewer, tuples)
        yield from ()

    return at_once()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--at-once", action="store_true", help="all steps of a field in one turn")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT / "src"))
    import napari
    import numpy as np
    import pandas  # noqa: F401 (the panels' workers import it ahead)
    from qtpy.QtWidgets import QApplication

    from napari_dvc_correct import layers as L
    from napari_dvc_correct import viewer_layers as V

    viewer = napari.Viewer(show=True)
    viewer.window._qt_window.resize(1400, 900)
    viewer.add_image(np.random.default_rng(0).random((96, 96, 96), np.float32), name="scan")
    app = QApplication.instance()
    for _ in range(20):
        app.processEvents()
        time.sleep(0.01)
    series = L.series_fields([_field((8, 8, 8), k) for k in range(4)])
    cases = [
        ("first field", L.field_layers(_field((13, 13, 13), 1), "uncorrected")),
        ("second field", L.field_layers(_field((13, 13, 13), 2), "corrected")),
        ("second again", L.field_layers(_field((13, 13, 13), 3), "corrected")),
        ("series", L.field_layers(series, "series (total)")),
    ]
    print(f"{'field':<14} {'step':>4} {'CPU ms':>7} {'wall ms':>8} {'then events CPU ms':>19}")
    for label, tuples in cases:
        steps = _steps(V, viewer, tuples)
        k, end = 0, False
        while not end:
            t0, w0 = time.thread_time(), time.perf_counter()
            while True:
                try:
                    next(steps)
                except StopIteration:
                    end = True
                if end or not args.at_once:
                    break
            t1, w1 = time.thread_time(), time.perf_counter()
            app.processEvents()  # what the step brings: the draw
            t2 = time.thread_time()
            print(
                f"{label:<14} {k:>4} {1000 * (t1 - t0):>7.0f} {1000 * (w1 - w0):>8.0f} "
                f"{1000 * (t2 - t1):>19.0f}",
                flush=True,
            )
            k += 1
    viewer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
