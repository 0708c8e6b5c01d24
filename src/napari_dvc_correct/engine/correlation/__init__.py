"""Local DVC: subvolume matching by IC-GN, its interpolation, initial guess, repair and noise."""
