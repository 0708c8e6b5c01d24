"""Scan series: the total and incremental strategies (paper Fig. 2)."""
