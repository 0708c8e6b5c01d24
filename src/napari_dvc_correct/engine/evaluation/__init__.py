"""Accuracy without ground truth: residuals, phases, eqs. 1-3, strain and error estimates."""
