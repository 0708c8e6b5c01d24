"""How well the evaluation's error estimate (voxels per node) follows the true error (issue 26).

Imposed-field cases with CT-like texture: a known field ``u`` makes the deformed scan
(``synthetic.make_pair``, 5th-order spline, independent noise on both scans); the evaluated
fields are ``u`` itself plus an error: small random errors everywhere (0.002-0.05 voxel, a
corrected field), and a smooth error of 0.2-1 voxel in a band (a field that missed a shear
band). Per field: the Spearman rank correlation of the estimate with the true error at the
nodes, the share of the nodes truly more than 0.5 voxel off that the estimate flags (> 0.5),
and the ratio of the medians (estimate / truth).

    python benchmarks/bench_error_estimate.py            # all cases, a table on stdout
    python benchmarks/bench_error_estimate.py --quick    # one texture, fewer fields

Results are written in docs/evaluation.md ("An error estimate in voxels").
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.stats import spearmanr

from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.synthetic import (
    add_noise,
    affine,
    concrete_ct_volume,
    ct_noise_sigma,
    make_pair,
    sample_displacement,
    two_phase_volume,
)

SHAPE = (64, 64, 64)
SUBVOLUME, STEP = 15, 5


def band_error(points, amplitude, width=12.0, center=32.0, direction=(0.3, 0.8, -0.5)):
    """A smooth error of ``amplitude`` voxels in a band across x (Gaussian profile)."""
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    profile = np.exp(-0.5 * ((points[:, 2] - center) / (width / 2.355)) ** 2)
    return amplitude * profile[:, None] * d[None, :]


def textures():
    yield (
        "concrete CT, 3 % noise",
        lambda s: concrete_ct_volume(s, aggregate_fraction=0.4, seed=3),
        0.03,
    )
    yield (
        "two-phase, sigma 3",
        lambda s: two_phase_volume(s, phase_grays=(100.0, 170.0), texture=4.0, seed=5),
        None,
    )


def cases(quick):
    rng = np.random.default_rng(0)
    # random errors of a DVC at this noise (about 0.05 voxel), and of a field twice as good
    fields = [
        ("exact", lambda p: np.zeros(p.shape)),
        ("0.02 random", lambda p: rng.normal(0, 0.02 / np.sqrt(3), p.shape)),
        ("0.05 random", lambda p: rng.normal(0, 0.05 / np.sqrt(3), p.shape)),
    ]
    amplitudes = (0.5, 1.0) if quick else (0.2, 0.5, 1.0)
    for a in amplitudes:
        fields.append(
            (
                f"band {a:g} + 0.05 random",
                lambda p, a=a: band_error(p, a) + rng.normal(0, 0.05 / np.sqrt(3), p.shape),
            )
        )
    if not quick:
        fields.append(
            (
                "uniform 0.3",
                lambda p: np.tile(np.array([0.3, 0.0, 0.0]), (len(p), 1)),
            )
        )
    return fields


def measure(estimate, truth, inside):
    e, t = estimate[inside], truth[inside]
    keep = np.isfinite(e)
    constant = np.ptp(t[keep]) == 0 if keep.any() else True
    rho = np.nan if constant or keep.sum() < 4 else spearmanr(e[keep], t[keep]).statistic
    bad = t > 0.5
    caught = float(np.mean(e[bad] > 0.5)) if bad.any() else np.nan
    false = float(np.mean(e[~bad] > 0.5)) if (~bad).any() else np.nan
    with np.errstate(divide="ignore"):
        ratio = float(np.median(np.where(np.isfinite(e), e, np.inf)) / np.median(t))
    return rho, caught, int(bad.sum()), false, ratio


def main(quick=False):
    gradient = np.array([[-0.01, 0.004, 0.0], [0.0, 0.006, 0.003], [0.002, 0.0, 0.008]])
    truth_function = affine(gradient, center=np.array(SHAPE) / 2.0, shift=(1.3, -0.7, 2.2))
    rows = []
    for label, make, noise in textures() if not quick else list(textures())[:1]:
        reference, deformed = make_pair(make, SHAPE, truth_function, 12)
        sigma = ct_noise_sigma(reference, noise) if noise else 3.0
        reference = add_noise(reference, sigma, seed=11)
        deformed = add_noise(deformed, sigma, seed=12)
        origin, step, shape = grid_for_volume(SHAPE, SUBVOLUME, STEP)
        base = DisplacementField.zeros(origin, step, shape, params={"subvolume": SUBVOLUME})
        points = base.points
        exact = sample_displacement(truth_function, points)
        fields, truths = {}, {}
        for name, error in cases(quick):
            e = error(points)
            fields[name] = base.replace(u=(exact + e).reshape((*shape, 3)))
            truths[name] = np.linalg.norm(e, axis=1).reshape(shape)
        started = time.perf_counter()
        result = evaluate_fields(reference, deformed, fields, keep_volumes=False)
        seconds = time.perf_counter() - started
        # nodes whose cell lies inside the specimen (the concrete is a cylinder in air)
        radius = 0.46 * SHAPE[1] - STEP if noise else np.inf
        r = np.hypot(points[:, 1] - (SHAPE[1] - 1) / 2, points[:, 2] - (SHAPE[2] - 1) / 2)
        inside = (r < radius).reshape(shape)
        for item in result.fields:
            rho, caught, n_bad, false, ratio = measure(
                item.error_estimate, truths[item.name], inside
            )
            rows.append(
                (
                    label,
                    item.name,
                    float(np.median(truths[item.name][inside])),
                    float(np.median(item.error_estimate[inside])),
                    ratio,
                    rho,
                    caught,
                    n_bad,
                    false,
                    item.accuracy,
                )
            )
        print(f"{label}: r0 {result.pair.background.mean:.4g}, {seconds:.1f} s", flush=True)
    print(
        "| texture | field | true median | estimated median | ratio | Spearman | caught > 0.5 "
        "(of) | false flags | p |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        label, name, t, e, ratio, rho, caught, n_bad, false, p = row
        print(
            f"| {label} | {name} | {t:.3f} | {e:.3f} | {ratio:.2f} | {rho:.2f} | "
            f"{'—' if np.isnan(caught) else f'{100 * caught:.0f} %'} ({n_bad}) | "
            f"{100 * false:.0f} % | {p:.4f} |"
        )
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    main(parser.parse_args().quick)
