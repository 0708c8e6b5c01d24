"""napari-dvc-correct."""
