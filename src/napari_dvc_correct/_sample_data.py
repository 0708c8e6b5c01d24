"""Sample data (npe2 ``sample_data`` contributions): made procedurally, deterministic, no download.

Two samples:

* a soil-like pair with poor texture (bright quartz grains in a darker clay matrix, weak texture,
  imaging noise) deformed by a known shear band plus a little uniaxial compression;
* a four-state scan series of the same material, loading step by step (a 4-D layer
  ``(state, z, y, x)``).

The known displacement of each deformed state is stored in the layer ``metadata`` under
``"dvc_correct"`` (``"truth"``: the keyword arguments of
:func:`napari_dvc_correct.engine.synthetic.shear_band`), so a user can compare a measurement with
the answer (:func:`true_field` rebuilds it on any POI grid).
"""

from __future__ import annotations

import numpy as np

from .engine.fields.field import DisplacementField
from .engine.synthetic import (
    add_noise,
    deform_volume,
    sample_displacement,
    shear_band,
    two_phase_volume,
)

#: Gray levels of the two phases (clay matrix, quartz grains), as in the paper's soil.
PHASE_GRAYS = (100.0, 170.0)
#: Standard deviation of the imaging noise added to every state (gray levels).
NOISE_SIGMA = 6.0


def shear_band_kwargs(shape, slip: float = 6.0, compression: float = 0.01) -> dict:
    """Keyword arguments of :func:`~napari_dvc_correct.engine.synthetic.shear_band` for a sample.

    The band runs diagonally through the centre of the volume (normal along z + x), one side
    slipping by ``slip`` voxels relative to the other, over a width of about ``shape / 12``;
    ``compression`` is the background uniaxial strain along z. A small rigid shift keeps the
    displacement non-zero everywhere, as in a real test rig.
    """
    shape = np.asarray(shape, dtype=np.float64)
    return {
        "center": [float(c) for c in (shape - 1) / 2.0],
        "width": float(max(3.0, shape.min() / 12.0)),
        "slip": float(slip),
        "normal": [1.0, 0.0, 1.0],
        "direction": [1.0, 0.0, -1.0],
        "background_strain": float(compression),
        "shift": [0.6, -0.4, 0.9],
    }


def soil_pair(
    shape=(96, 96, 96), slip: float = 6.0, compression: float = 0.01, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Reference and deformed soil-like volumes with a known shear-band deformation.

    Parameters
    ----------
    shape : tuple of 3 ints
        ``(nz, ny, nx)`` in voxels.
    slip : float
        Relative slip across the shear band, voxels.
    compression : float
        Background uniaxial compressive strain along z.
    seed : int
        Random seed (the result is deterministic given the arguments).

    Returns
    -------
    reference, deformed : ndarray, float32, shape ``shape``
        Gray values around :data:`PHASE_GRAYS` plus noise of :data:`NOISE_SIGMA`.
    truth : dict
        Keyword arguments of :func:`~napari_dvc_correct.engine.synthetic.shear_band` giving the
        displacement ``u(X)`` (z, y, x voxels) with ``F(X + u(X)) = G(X)``.
    """
    clean = two_phase_volume(shape, phase_grays=PHASE_GRAYS, seed=seed)
    truth = shear_band_kwargs(shape, slip, compression)
    deformed = deform_volume(clean, shear_band(**truth))
    reference = add_noise(clean, NOISE_SIGMA, seed=seed + 1)
    deformed = add_noise(deformed, NOISE_SIGMA, seed=seed + 2)
    return reference, deformed, truth


def scan_series(
    shape=(64, 64, 64), slips=(0.0, 2.0, 4.5, 7.0), seed: int = 0
) -> tuple[np.ndarray, list[dict]]:
    """A scan series: the same soil-like sample under increasing shear.

    Parameters
    ----------
    shape : tuple of 3 ints
        ``(nz, ny, nx)`` of each state, voxels.
    slips : sequence of float
        Total slip of the shear band at each state (the first state is the reference, usually 0).
    seed : int
        Random seed.

    Returns
    -------
    series : ndarray, float32, shape ``(n_states, nz, ny, nx)``
    truths : list of dict
        For each state, the keyword arguments of the total displacement (from state 0) for
        :func:`~napari_dvc_correct.engine.synthetic.shear_band`.
    """
    clean = two_phase_volume(shape, phase_grays=PHASE_GRAYS, seed=seed)
    states, truths = [], []
    for index, slip in enumerate(slips):
        fraction = slip / max(slips) if max(slips) > 0 else 0.0
        truth = shear_band_kwargs(shape, slip, compression=0.01 * fraction)
        truth["shift"] = [s * fraction for s in truth["shift"]]
        volume = clean if slip == 0 and fraction == 0 else deform_volume(clean, shear_band(**truth))
        states.append(add_noise(volume, NOISE_SIGMA, seed=seed + 1 + index))
        truths.append(truth)
    return np.stack(states), truths


def true_field(truth: dict, origin, step, shape) -> DisplacementField:
    """The known displacement of a sample on a POI grid, as a :class:`DisplacementField`.

    Parameters
    ----------
    truth : dict
        Keyword arguments of :func:`~napari_dvc_correct.engine.synthetic.shear_band`.
    origin, step, shape : tuples of 3
        The grid (z, y, x), voxels.
    """
    grid = DisplacementField.zeros(origin, step, shape)
    u = sample_displacement(shear_band(**truth), grid.points).reshape(*grid.shape, 3)
    return grid.replace(u=u, metadata={"source": "known answer", "truth": truth})


def _role(role: str, **extra) -> dict:
    return {"dvc_correct": {"role": role, **extra}}


def make_soil_shear_band() -> list[tuple]:
    """npe2 sample: the soil-like pair (96³ voxels) as two Image layers."""
    reference, deformed, truth = soil_pair()
    contrast = [float(PHASE_GRAYS[0] - 30), float(PHASE_GRAYS[1] + 30)]
    return [
        (
            reference,
            {"name": "reference", "contrast_limits": contrast, "metadata": _role("reference")},
            "image",
        ),
        (
            deformed,
            {
                "name": "deformed",
                "contrast_limits": contrast,
                "metadata": _role("deformed", truth=truth),
                "visible": False,
            },
            "image",
        ),
    ]


def make_scan_series() -> list[tuple]:
    """npe2 sample: a four-state scan series (64³ voxels each) as one 4-D Image layer."""
    series, truths = scan_series()
    contrast = [float(PHASE_GRAYS[0] - 30), float(PHASE_GRAYS[1] + 30)]
    return [
        (
            series,
            {
                "name": "scan series",
                "contrast_limits": contrast,
                "metadata": _role("series", truths=truths),
            },
            "image",
        )
    ]
