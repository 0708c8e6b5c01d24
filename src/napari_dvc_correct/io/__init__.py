"""Readers and writers for volumes and displacement fields (no Qt, no napari)."""
