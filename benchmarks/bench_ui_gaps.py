"""How long the main thread stalls while each panel runs: the longest gap between ticks of a
timer on the main (Qt) thread, from Run to the result on the canvas, per panel.

A user feels a gap as a frozen window: no redraw, no slider, no Cancel. The panels run their
engine work in thread workers and touch layers only in the ``yielded``/``returned`` slots, so a
gap comes from (a) the result handling in those slots, (b) a worker holding the GIL for long
(numba compiling a kernel, a long numpy call) or (c) napari drawing new layers. The benchmark
times the slots too, to say which.

The run is what a user does on the sample pair: Correlate (twice: the first run may compile
kernels, ``--cold`` forces that with an empty numba cache), Self-correct, Evaluate (two
phases), Export (one ``.dvcfield``), each through its panel in a shown viewer (run it under
Xvfb: ``xvfb-run -a``). ``--series`` adds a 4-state series (64³ each, as four 3-D layers):
series Correlate (incremental), series Self-correct (1 pass) and Evaluate of every field
listed (the pair's and the series'); ``--only-series`` runs only those. ``--main-profile``
profiles the main thread alone from Run to settled, per run (top functions printed; the
profiles saved as ``ui_gaps_main_<n>.prof`` in the temporary folder). Beside each run's
longest wall gap, the longest main-thread CPU of a gap ("gap CPU ms", ``time.thread_time``):
what the load of a shared machine does not stretch. A result shown in steps (one layer per turn
of the event loop) is waited for. Figures go to stdout
and, with ``--json``, to a file; they belong in docs/performance.md with the machine and its
load.

    xvfb-run -a python benchmarks/bench_ui_gaps.py [--size 96] [--subvolume 21] [--step 6]
                                                   [--tick-ms 5] [--cold] [--series]
                                                   [--main-profile] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _arguments(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=96, help="edge of the cubic pair (voxels)")
    parser.add_argument("--subvolume", type=int, default=21)
    parser.add_argument("--step", type=int, default=6)
    parser.add_argument("--tick-ms", type=float, default=5.0, help="main-thread timer interval")
    parser.add_argument("--cold", action="store_true", help="an empty numba cache (compile all)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--profile", action="store_true", help="profile the result slots (cProfile, top 25)"
    )
    parser.add_argument(
        "--series",
        action="store_true",
        help="also a 4-state series (64³ each): series Correlate, Self-correct, Evaluate",
    )
    parser.add_argument(
        "--only-series", action="store_true", help="the series runs only (not the pair's)"
    )
    parser.add_argument(
        "--main-profile",
        action="store_true",
        help="profile the main thread of each run, Run to settled (cProfile, top 30 by own time)",
    )
    parser.add_argument(
        "--why", action="store_true", help="print every thread's stack during gaps over 150 ms"
    )
    return parser.parse_args(argv)


#: With ``--main-profile``: (panel, cProfile of the main thread) of each run, in order.
MAIN_PROFILES: list | None = None

#: The main thread's CPU clock (``time.thread_time``) at each tick, beside the wall clock: the
#: CPU a gap took on the main thread, which the machine's load does not stretch (drawing by
#: Mesa's llvmpipe threads is not in it).
CPU_TICKS: list[float] = []


def _tick(ticks: list) -> None:
    ticks.append(time.perf_counter())
    CPU_TICKS.append(time.thread_time())


class GapWatch:
    """A watchdog thread: while the main thread has not ticked for ``limit_s``, it samples
    every thread's stack (where the main thread is stuck, and what the workers do)."""

    def __init__(self, ticks: list, limit_s: float = 0.15) -> None:
        import threading

        self.ticks, self.limit_s = ticks, limit_s
        self.samples: list[str] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._watch, daemon=True)
        self.main = threading.main_thread().ident
        self.thread.start()

    def _watch(self) -> None:
        import traceback

        while not self.stop.wait(0.05):
            last = self.ticks[-1] if self.ticks else None
            silent = time.perf_counter() - last if last is not None else 0.0
            if silent < self.limit_s:
                continue
            lines = [f"-- main thread silent for {silent:.2f} s"]
            for ident, frame in sys._current_frames().items():
                if ident == self.thread.ident:
                    continue
                stack = traceback.extract_stack(frame)
                ours = [f for f in stack if "napari_dvc_correct" in f.filename]
                if ident != self.main and not ours:
                    continue  # idle helper threads
                shown = ours[-4:] + [f for f in stack[-2:] if f not in ours]
                lines.append(f"   {'MAIN' if ident == self.main else 'worker'}:")
                lines += [
                    f"      {f.filename.split('site-packages/')[-1].split('src/')[-1]}:"
                    f"{f.lineno} {f.name}"
                    for f in shown
                ]
            self.samples.append("\n".join(lines))


class SlotClock:
    """Wall time spent in the panels' main-thread slots (``_on_yielded``, ``_on_returned``)."""

    def __init__(self) -> None:
        self.spans: list[tuple[str, float, float]] = []

    def wrap(self, cls, name: str, profile=None) -> None:
        original = getattr(cls, name)
        clock = self

        def timed(self, *args, **kwargs):
            start = time.perf_counter()
            if profile is not None:
                profile.enable()
            try:
                return original(self, *args, **kwargs)
            finally:
                if profile is not None:
                    profile.disable()
                clock.spans.append((name, start, time.perf_counter()))

        setattr(cls, name, timed)

    def longest(self, name: str, since: float) -> float:
        spans = [end - start for slot, start, end in self.spans if slot == name and start >= since]
        return max(spans, default=0.0)


def run_panel(
    widget, ticks: list, slots: SlotClock, settle_ms: int = 500, main_profile=None
) -> dict:
    """Run ``widget`` as the Run button does; the longest main-thread gap and where it was.

    ``main_profile`` (a ``cProfile.Profile``) profiles the main thread only (cProfile follows
    the thread that enables it) from Run to the end of the settling time: the slots and what
    napari and Qt do after them (drawing the new layers, the plots)."""
    from qtpy.QtCore import QCoreApplication, QEventLoop, QTimer

    ticks.clear()
    CPU_TICKS.clear()
    worker = widget.run(start=False)
    if worker is None:
        raise RuntimeError(f"{type(widget).__name__}: {widget.message.text()}")
    loop = QEventLoop()
    worker.finished.connect(loop.quit)
    _tick(ticks)
    started = ticks[-1]
    if main_profile is None and MAIN_PROFILES is not None:
        import cProfile

        main_profile = cProfile.Profile()
        MAIN_PROFILES.append((type(widget).__name__, main_profile))
    if main_profile is not None:
        main_profile.enable()
    worker.start()
    loop.exec()
    while widget.running:  # the result shown in steps after the worker ends
        QCoreApplication.processEvents(QEventLoop.ProcessEventsFlag.WaitForMoreEvents, 50)
    finished = time.perf_counter()
    QTimer.singleShot(settle_ms, loop.quit)  # what the result brings after (drawing the layers)
    loop.exec()
    if main_profile is not None:
        main_profile.disable()
    _tick(ticks)
    gaps = [(b - a, a) for a, b in zip(ticks, ticks[1:])]
    gap, at = max(gaps)
    cpu_gap = max(b - a for a, b in zip(CPU_TICKS, CPU_TICKS[1:]))
    if widget.last_error:
        raise RuntimeError(f"{type(widget).__name__}: {widget.last_error}")
    return {
        "run_s": finished - started,
        "longest_gap_ms": 1000 * gap,
        "longest_gap_cpu_ms": 1000 * cpu_gap,
        "gap_at_s": at - started,
        "longest_returned_slot_ms": 1000 * slots.longest("_on_returned", started),
        "longest_yielded_slot_ms": 1000 * slots.longest("_on_yielded", started),
    }


def run_series(viewer, panels, ticks, slots, args) -> dict:
    """A 4-state series (64³ each, the sample's shear) as four 3-D layers: series Correlate
    (incremental), series Self-correct (1 pass), Evaluate of every field on the panel's list."""
    from napari_dvc_correct._sample_data import scan_series

    series, _ = scan_series()
    names = [f"state {k}" for k in range(len(series))]
    for name, volume in zip(names, series):
        viewer.add_image(volume, name=name)
    correlate = panels["Correlate"]
    correlate.mode.setCurrentIndex(correlate.mode.findData("series"))
    correlate.set_series_layers(names)
    correlate.strategy.setCurrentIndex(correlate.strategy.findData("incremental"))
    correlate.subvolume.setValue(21)
    correlate.step.setValue(6)
    correlate._update.flush()
    results = {"series Correlate": run_panel(correlate, ticks, slots)}
    correct = panels["Self-correct"]
    correct.field.setCurrentIndex(correct.field.findText("series (incremental)"))
    correct.max_passes.setValue(1)
    results["series Self-correct"] = run_panel(correct, ticks, slots)
    evaluate = panels["Evaluate"]
    evaluate.reference.set_layer(names[0])
    evaluate.deformed.set_layer(names[-1])
    evaluate.n_phases.setValue(2)
    results["series Evaluate"] = run_panel(evaluate, ticks, slots)
    return results


def main(argv=None) -> int:
    args = _arguments(argv)
    global MAIN_PROFILES
    MAIN_PROFILES = [] if args.main_profile else None
    if args.cold:
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="numba-cold-")
    sys.path.insert(0, str(ROOT / "src"))
    import cProfile

    import napari
    import numpy as np
    from qtpy.QtCore import QTimer

    from napari_dvc_correct._sample_data import soil_pair
    from napari_dvc_correct.widgets._base import EngineWidget

    slots = SlotClock()
    profile = cProfile.Profile() if args.profile else None
    slots.wrap(EngineWidget, "_on_returned", profile)
    slots.wrap(EngineWidget, "_on_yielded")
    reference, deformed, _ = soil_pair((args.size,) * 3, slip=3.0, compression=0.01)
    viewer = napari.Viewer(show=True)
    viewer.window._qt_window.resize(1400, 900)
    viewer.add_image(reference.astype(np.float32), name="reference")
    viewer.add_image(deformed.astype(np.float32), name="deformed")
    panels = {}
    for name in ("Correlate", "Self-correct", "Evaluate", "Export"):
        _, panels[name] = viewer.window.add_plugin_dock_widget(
            "napari-dvc-correct", name, tabify=bool(panels)
        )
    ticks: list[float] = []
    timer = QTimer()
    timer.setInterval(max(1, int(round(args.tick_ms))))
    timer.timeout.connect(lambda: _tick(ticks))
    timer.start()
    watch = GapWatch(ticks) if args.why else None

    correlate = panels["Correlate"]
    correlate.subvolume.setValue(args.subvolume)
    correlate.step.setValue(args.step)
    correlate.preview.setChecked(False)
    results = {}
    if not args.only_series:
        results["Correlate (first)"] = run_panel(correlate, ticks, slots)
        results["Correlate (again)"] = run_panel(correlate, ticks, slots)
        panels["Self-correct"].max_passes.setValue(2)
        results["Self-correct"] = run_panel(panels["Self-correct"], ticks, slots)
        panels["Evaluate"].n_phases.setValue(2)
        results["Evaluate"] = run_panel(panels["Evaluate"], ticks, slots)
        with tempfile.TemporaryDirectory() as folder:
            export = panels["Export"]
            export.set_format(".dvcfield")
            export.path.setText(str(Path(folder) / "bench.dvcfield"))
            results["Export"] = run_panel(export, ticks, slots)
    if args.series or args.only_series:
        results.update(run_series(viewer, panels, ticks, slots, args))
    timer.stop()
    if profile is not None:
        import pstats

        pstats.Stats(profile).sort_stats("cumulative").print_stats(40)
    for index, (panel, main_profile) in enumerate(MAIN_PROFILES or []):
        import pstats

        main_profile.dump_stats(Path(tempfile.gettempdir()) / f"ui_gaps_main_{index}.prof")

        print(f"==== main thread, {panel}")
        pstats.Stats(main_profile).sort_stats("tottime").print_stats(30)
        pstats.Stats(main_profile).sort_stats("cumulative").print_stats(45)
    if watch is not None:
        watch.stop.set()
        print("\n\n".join(watch.samples))

    pois = int(np.prod([len(range(0, args.size - args.subvolume + 1, args.step))] * 3))
    print(
        f"pair {args.size}³, subvolume {args.subvolume}, step {args.step} (~{pois} POIs), "
        f"timer {args.tick_ms:g} ms, numba cache {'cold' if args.cold else 'as found'}"
    )
    print(
        f"{'panel':<20} {'run s':>7} {'longest gap ms':>15} {'at s':>6} {'returned slot ms':>17} "
        f"{'gap CPU ms':>11}"
    )
    for name, row in results.items():
        print(
            f"{name:<20} {row['run_s']:>7.2f} {row['longest_gap_ms']:>15.0f} "
            f"{row['gap_at_s']:>6.2f} {row['longest_returned_slot_ms']:>17.0f} "
            f"{row['longest_gap_cpu_ms']:>11.0f}"
        )
    if args.json:
        settings = {k: v for k, v in vars(args).items() if k != "json"}
        args.json.write_text(json.dumps({"settings": settings, "panels": results}, indent=2))
    viewer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
