"""One module per use of the engine, shared by the panels and the command line: takes the
fields and the options, writes or computes, yields progress (no Qt, no napari)."""
