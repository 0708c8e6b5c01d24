"""Subcommands of the command line (see :mod:`napari_dvc_correct.cli`)."""
