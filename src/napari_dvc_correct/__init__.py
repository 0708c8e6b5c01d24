"""napari-dvc-correct: self-correcting digital volume correlation of CT scans, in napari and on the command line."""
