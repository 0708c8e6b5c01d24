"""Run ``napari-dvc-correct ARGS`` unchanged except for one pause, so a test can signal it there.

``NDC_PAUSE_AT`` names the moment; on reaching it the process writes ``PAUSED <moment>`` to
stderr and sleeps (at most 60 s), so the test's SIGINT/SIGTERM/SIGKILL lands exactly there:

- ``compute``: after the first progress report of the engine (the work has started);
- ``write``: inside the atomic write of a field file, after part of it is on disk;
- ``set``: inside an output set, after its first file is written (series: ``state_01.npz``;
  evaluate: the tables and plots, before ``report.md``);
- ``scratch``: right after a tiled self-correction made its folder of temporary arrays;
- ``swap``: an output set's swap, while the earlier set is removed (signals held back, 2 s);
- ``written``: ``correlate`` after its field file is complete, before its summary line;
- ``swallowed``: a library that catches every exception (as numba loading its cache did), 3 s.

Nothing else is changed: the same ``cli.main``, signal handlers and writers run.
"""

from __future__ import annotations

import os
import sys
import time


def pause(moment: str, seconds: float = 60) -> None:
    sys.stderr.write(f"PAUSED {moment}\n")
    sys.stderr.flush()
    time.sleep(seconds)


def install(moment: str) -> None:
    if moment == "compute":
        from napari_dvc_correct.commands import _common

        update = _common.ProgressBar.update

        def paused_update(self, progress):
            update(self, progress)
            pause("compute")

        _common.ProgressBar.update = paused_update
    elif moment == "write":
        import numpy as np

        def partial_savez(stream, **arrays):
            stream.write(b"PK\x03\x04 half a field file")
            stream.flush()
            pause("write")

        np.savez_compressed = partial_savez
    elif moment == "set":
        from napari_dvc_correct.io import npz
        from napari_dvc_correct.report import markdown  # write_report imports it when it runs

        save_field = npz.save_field
        calls = []

        def paused_save(field, path):
            save_field(field, path)
            calls.append(path)
            if len(calls) == 1:
                pause("set")

        def paused_markdown(text, path):
            pause("set")

        npz.save_field = paused_save
        markdown.write_markdown = paused_markdown
    elif moment == "scratch":
        from napari_dvc_correct.tiled import correction

        scratch_dir = correction.scratch_dir

        def paused_scratch(prefix, parent=None):
            path = scratch_dir(prefix, parent)
            pause("scratch")
            return path

        correction.scratch_dir = paused_scratch
    elif moment == "swap":
        from napari_dvc_correct.io import atomic

        rmtree = atomic.shutil.rmtree

        def paused_rmtree(path, *args, **kwargs):
            if atomic.TEMP_MARK in str(path) and os.path.exists(path):
                pause("swap", 2)  # signals are held back here: it lands when the swap is done
            return rmtree(path, *args, **kwargs)

        atomic.shutil.rmtree = paused_rmtree
    elif moment == "written":
        from napari_dvc_correct.commands import correlate

        summary = correlate.summary

        def paused_summary(*args):
            pause("written")
            return summary(*args)

        correlate.summary = paused_summary
    elif moment == "swallowed":
        from napari_dvc_correct.engine import backend

        select = backend.select_device

        def swallowing_select(*args, **kwargs):  # as a library that catches every exception
            try:
                pause("swallowed", 3)
            except BaseException:
                pass
            return select(*args, **kwargs)

        backend.select_device = swallowing_select
    elif moment:
        raise SystemExit(f"unknown NDC_PAUSE_AT {moment!r}")


if __name__ == "__main__":
    install(os.environ.get("NDC_PAUSE_AT", ""))
    from napari_dvc_correct import cli

    sys.exit(cli.main(sys.argv[1:]))
