"""The self-correcting strategy (paper Fig. 3): clean, densify, warp, correlate again, update."""
