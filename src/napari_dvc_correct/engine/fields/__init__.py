"""The data model and its operations: grid and scattered fields, splines, composition, warps."""
