"""One module per use, shared by the command line and the panels.

Each takes the volumes (arrays, or lazily read volumes out of core), the option records and a
:class:`..engine.run_options.RunOptions`, and chooses in memory or out of core in one place
(:attr:`RunOptions.out_of_core`). Above the engine, :mod:`..tiled` and :mod:`..io`; below
:mod:`..commands` and :mod:`..widgets`. Each is a generator yielding
:class:`..engine.progress.Progress` and returning its result.
"""
