"""How well the evaluation's error estimate (voxels per node) follows the true error.

Imposed-field cases: a known affine field ``u`` makes the deformed scan from a larger pattern
(our 5th-order spline, or scipy's ``map_coordinates`` of order 1 or 3: another interpolator
than the evaluation's), independent noise on both scans; the evaluated fields are ``u`` itself
plus an error: random errors independent from node to node (0.02-0.2 voxel; 0.02 is what a
corrected field holds), a smooth error of 0.2-1 voxel in a band (a field that missed a shear
band; a narrow 0.6-voxel band puts many nodes at 0.5-0.6), a uniform 0.3 and 1.0 voxel, and
the field measured by our DVC (subvolume 15, step 5: errors at the noise level, with the
match's noise uncertainty) and that field corrected by our self-correction; and on a second pair
of the same texture whose true field holds a narrow shear band on a rotation, our DVC's field
plain and corrected (a true field that bends at the grid's scale). Per field: the Spearman rank correlation of the estimate with the true
error at the nodes, the share of the nodes truly more than 0.5 voxel off that the estimate
flags as likely (P >= 1/2) and possibly (P >= 16 %) above 0.5 voxel
(``error_estimate.probability_above``), the share of the others it flags (false flags), the
ratio of the medians (estimate / truth), the share of nodes below the residual's resolution
(there the estimate is a bound, not a rank) and the median of the *window's* true error: the
densified error field averaged over each node's window (what a window's residual can see at
best; independent node errors average out in it) and, for our DVC's fields, the median of
the match's recorded noise uncertainty ``|σ_u|`` that the estimate adds below the resolution
(a corrected field's record decides its reading there).

    python benchmarks/bench_error_estimate.py              # all cases, a table on stdout
    python benchmarks/bench_error_estimate.py --quick      # one texture, fewer fields
    python benchmarks/bench_error_estimate.py --correlated # the correlated-noise textures only
    python benchmarks/bench_error_estimate.py --apply-correlation  # the estimate uses the measured
                                                                  # noise correlation (off by default)

Two textures carry spatially correlated noise (white noise smoothed by a Gaussian of ``s`` voxels,
then scaled back to its σ: correlation ``exp(−k²/(4s²))`` at lag ``k``), as CT reconstruction
leaves it; the pair's measured noise correlation (``pair.noise_correlation``, lags 1-3 along z)
is printed with each texture.

Results are written in docs/evaluation.md ("An error estimate in voxels").
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import ndimage
from scipy.stats import spearmanr

from napari_dvc_correct.engine.correction.self_correction import correct
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.evaluation.error_estimate import (
    LIKELY,
    POSSIBLY,
    error_region_half,
    noise_error,
    probability_above,
)
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.fields.field_spline import densify
from napari_dvc_correct.engine.synthetic import (
    add_noise,
    affine,
    band_rotation_bending,
    concrete_ct_volume,
    ct_noise_sigma,
    invert_displacement,
    make_pair,
    sample_displacement,
    textured_volume,
    two_phase_volume,
)

SHAPE = (64, 64, 64)
SUBVOLUME, STEP = 15, 5


def make_pair_with(pattern, shape, displacement, order, margin=12):
    """As :func:`synthetic.make_pair`, the deformed scan by scipy's ``map_coordinates`` of
    ``order`` (1: trilinear, 3: cubic spline) instead of our 5th-order spline."""
    big = pattern(tuple(n + 2 * margin for n in shape)).astype(np.float64)
    positions = np.indices(big.shape).reshape(3, -1).T.astype(np.float64)
    source = invert_displacement(lambda p: displacement(np.asarray(p) - margin), positions)
    deformed = ndimage.map_coordinates(big, source.T, order=order, mode="mirror")
    deformed = deformed.reshape(big.shape).astype(np.float32)
    crop = tuple(slice(margin, margin + n) for n in shape)
    return np.ascontiguousarray(big[crop], np.float32), np.ascontiguousarray(deformed[crop])


def band_error(points, amplitude, width=12.0, center=32.0, direction=(0.3, 0.8, -0.5)):
    """A smooth error of ``amplitude`` voxels in a band across x (Gaussian profile)."""
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    profile = np.exp(-0.5 * ((points[:, 2] - center) / (width / 2.355)) ** 2)
    return amplitude * profile[:, None] * d[None, :]


def textures(correlated_only=False):
    """(label, pattern, noise as a share of the p1-p99 range or a gray sigma, and the Gaussian
    smoothing of the noise in voxels (0: white), warp order, cylinder specimen)."""
    if not correlated_only:
        yield from _white_textures()
    yield (
        "concrete CT, 3 % noise smoothed 0.7",
        lambda s: concrete_ct_volume(s, aggregate_fraction=0.4, seed=3),
        ("share", 0.03, 0.7),
        5,
        True,
    )
    yield (  # held out: another texture, another correlation length
        "two-phase, sigma 3 smoothed 1.0, cubic warp",
        lambda s: two_phase_volume(s, phase_grays=(100.0, 170.0), texture=4.0, seed=9),
        ("sigma", 3.0, 1.0),
        3,
        False,
    )


def _white_textures():
    yield (
        "concrete CT, 3 % noise",
        lambda s: concrete_ct_volume(s, aggregate_fraction=0.4, seed=3),
        ("share", 0.03, 0.0),
        5,
        True,
    )
    yield (
        "two-phase, sigma 3",
        lambda s: two_phase_volume(s, phase_grays=(100.0, 170.0), texture=4.0, seed=5),
        ("sigma", 3.0, 0.0),
        5,
        False,
    )
    yield (
        "concrete CT seed 8, 5 % noise, trilinear warp",
        lambda s: concrete_ct_volume(s, aggregate_fraction=0.3, seed=8),
        ("share", 0.05, 0.0),
        1,
        True,
    )
    yield (
        "concrete CT seed 21, 4 % noise, cubic warp",
        lambda s: concrete_ct_volume(s, aggregate_fraction=0.35, seed=21),
        ("share", 0.04, 0.0),
        3,
        True,
    )
    yield (
        "speckle 1.5, sigma 4, cubic warp",
        lambda s: 200.0 * textured_volume(s, 1.5, seed=7),
        ("sigma", 4.0, 0.0),
        3,
        False,
    )


def cases(quick):
    rng = np.random.default_rng(0)
    # random errors of a DVC at this noise (about 0.05 voxel), and of a field twice as good
    fields = [
        ("exact", lambda p: np.zeros(p.shape)),
        ("0.02 random", lambda p: rng.normal(0, 0.02 / np.sqrt(3), p.shape)),
        ("0.05 random", lambda p: rng.normal(0, 0.05 / np.sqrt(3), p.shape)),
        ("0.2 random", lambda p: rng.normal(0, 0.2 / np.sqrt(3), p.shape)),
    ]
    amplitudes = (0.5, 1.0) if quick else (0.2, 0.5, 1.0)
    for a in amplitudes:
        fields.append(
            (
                f"band {a:g} + 0.05 random",
                lambda p, a=a: band_error(p, a) + rng.normal(0, 0.05 / np.sqrt(3), p.shape),
            )
        )
    # a narrow band whose many nodes lie just above 0.5 voxel (0.5-0.6 at the band's edges)
    fields.append(
        (
            "band 0.6 narrow + 0.05 random",
            lambda p: band_error(p, 0.6, width=8.0) + rng.normal(0, 0.05 / np.sqrt(3), p.shape),
        )
    )
    if not quick:
        fields.append(
            (
                "uniform 0.3",
                lambda p: np.tile(np.array([0.3, 0.0, 0.0]), (len(p), 1)),
            )
        )
        fields.append(
            (
                "uniform 1.0",
                lambda p: np.tile(np.array([0.0, 0.6, 0.8]), (len(p), 1)),
            )
        )
    return fields


def dvc_field(reference, deformed):
    """Our DVC's field on the pair (subvolume 15, step 5), with its noise uncertainty."""
    return correlate(reference, deformed, CorrelationParams(subvolume=SUBVOLUME, step=STEP))


def smoothed_noise(volume, sigma, smoothing, seed):
    """``volume`` plus Gaussian noise of standard deviation ``sigma`` smoothed by a Gaussian of
    ``smoothing`` voxels and scaled back to ``sigma`` (0: white, :func:`synthetic.add_noise`)."""
    if smoothing <= 0:
        return add_noise(volume, sigma, seed=seed)
    noise = np.random.default_rng(seed).normal(0.0, 1.0, volume.shape)
    noise = ndimage.gaussian_filter(noise, smoothing, mode="wrap")
    return (volume + sigma * noise / noise.std()).astype(np.float32)


def noisy_pair(make, truth, order, kind, noise, seeds, smoothing=0.0):
    """The reference and the deformed scan of ``truth`` (warped with a 5th-order spline, or with
    scipy's ``order`` where it is not 5), each with its own noise: ``noise`` as a share of the
    texture's contrast (``kind == "share"``) or as a gray-level σ, smoothed by ``smoothing``
    voxels (:func:`smoothed_noise`)."""
    if order == 5:
        reference, deformed = make_pair(make, SHAPE, truth, 12)
    else:
        reference, deformed = make_pair_with(make, SHAPE, truth, order)
    sigma = ct_noise_sigma(reference, noise) if kind == "share" else noise
    return (
        smoothed_noise(reference, sigma, smoothing, seeds[0]),
        smoothed_noise(deformed, sigma, smoothing, seeds[1]),
    )


def band_fields(make, kind, noise, order, fields, truths, smoothing=0.0):
    """Our DVC's field, plain and corrected, of a pair whose true field is a narrow shear band
    (half-width 4 voxels, slip 2.8: narrower than a subvolume) on a rotation, bending and a
    translation: a true field that is not smooth at the grid's scale, which the plain field
    misses at the band's core (0-13 nodes truly more than 0.5 voxel off, by texture)."""
    truth = band_rotation_bending((SHAPE[0] / 2,) * 3, 4.0, 2.8)
    reference, deformed = noisy_pair(make, truth, order, kind, noise, (21, 22), smoothing)
    params = CorrelationParams(subvolume=SUBVOLUME, step=STEP)
    measured = dvc_field(reference, deformed)
    corrected = correct(reference, deformed, measured, params)
    for name, item in (("narrow band DVC", measured), ("narrow band DVC corrected", corrected)):
        error = item.u.reshape(-1, 3) - sample_displacement(truth, item.points)
        truths[name] = np.linalg.norm(error, axis=1).reshape(item.shape)
        fields[name] = (item, reference, deformed)


def window_truth(base, error, half):
    """|window mean| of the densified true error around each node (voxels, the grid)."""
    dense = densify(base.replace(u=error.reshape((*base.shape, 3))), shape=SHAPE, dtype=float)
    size = 2 * half + 1
    mean = np.stack(
        [ndimage.uniform_filter(dense[..., c], size, mode="nearest") for c in range(3)], -1
    )
    nodes = np.round(base.points).astype(int)
    return np.linalg.norm(mean[nodes[:, 0], nodes[:, 1], nodes[:, 2]], axis=1).reshape(base.shape)


def measure(estimate, truth, inside, resolution, windowed, match_sigma=None):
    e, t, limit = estimate[inside], truth[inside], resolution[inside]
    keep = np.isfinite(e)
    constant = np.ptp(t[keep]) == 0 if keep.any() else True
    rho = np.nan if constant or keep.sum() < 4 else spearmanr(e[keep], t[keep]).statistic
    p = probability_above(e, limit)
    bad = t > 0.5

    def share(flags, where):
        return float(np.mean(flags[where])) if where.any() else np.nan

    below = float(np.mean(~(e > np.where(np.isnan(limit), np.inf, limit))))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = float(np.median(np.where(np.isfinite(e), e, np.inf)) / np.median(t))
    return dict(
        rho=rho, n_bad=int(bad.sum()), caught=share(p >= LIKELY, bad),
        false=share(p >= LIKELY, ~bad), caught_possibly=share(p >= POSSIBLY, bad),
        false_possibly=share(p >= POSSIBLY, ~bad), ratio=ratio, below=below,
        true_median=float(np.median(t)), estimated_median=float(np.median(e)),
        window_median=float(np.median(windowed[inside])) if windowed is not None else np.nan,
        resolution=float(np.median(np.where(np.isnan(limit), np.inf, limit))),
        match_sigma=np.nan if match_sigma is None else float(np.median(match_sigma[inside])),
    )  # fmt: skip


def _number(value):
    return "—" if np.isnan(value) else f"{value:.3f}"


def percent(value):
    return "—" if np.isnan(value) else f"{100 * value:.0f} %"


def main(quick=False, correlated_only=False):
    gradient = np.array([[-0.01, 0.004, 0.0], [0.0, 0.006, 0.003], [0.002, 0.0, 0.008]])
    truth_function = affine(gradient, center=np.array(SHAPE) / 2.0, shift=(1.3, -0.7, 2.2))
    rows = []
    chosen = list(textures(correlated_only))[: 1 if quick else None]
    for label, make, (kind, noise, smoothing), order, cylinder in chosen:
        reference, deformed = noisy_pair(
            make, truth_function, order, kind, noise, (11, 12), smoothing
        )
        origin, step, shape = grid_for_volume(SHAPE, SUBVOLUME, STEP)
        base = DisplacementField.zeros(origin, step, shape, params={"subvolume": SUBVOLUME})
        points = base.points
        exact = sample_displacement(truth_function, points)
        fields, truths, windows = {}, {}, {}
        for name, error in cases(quick):
            e = error(points)
            fields[name] = base.replace(u=(exact + e).reshape((*shape, 3)))
            truths[name] = np.linalg.norm(e, axis=1).reshape(shape)
            windows[name] = window_truth(base, e, error_region_half(base))
        if not quick:
            band_fields(make, kind, noise, order, fields, truths, smoothing)
            measured = dvc_field(reference, deformed)
            corrected = correct(
                reference,
                deformed,
                measured,
                CorrelationParams(subvolume=SUBVOLUME, step=STEP),
            )
            for name, item in (
                ("DVC (with its uncertainty)", measured),
                ("DVC corrected", corrected),
            ):
                fields[name] = item
                error = item.u.reshape(-1, 3) - sample_displacement(truth_function, item.points)
                truths[name] = np.linalg.norm(error, axis=1).reshape(item.shape)
        own_pair = {k: v for k, v in fields.items() if isinstance(v, tuple)}
        fields = {k: v for k, v in fields.items() if not isinstance(v, tuple)}
        started = time.perf_counter()
        result = evaluate_fields(reference, deformed, fields, keep_volumes=False)
        seconds = time.perf_counter() - started
        items = list(result.fields)
        if own_pair:  # the band's pair: its own r0 and map
            first = next(iter(own_pair.values()))
            band = {k: v[0] for k, v in own_pair.items()}
            items += list(evaluate_fields(first[1], first[2], band, keep_volumes=False).fields)
        for item in items:
            # nodes whose window lies inside the specimen (the concrete is a cylinder in air)
            p = item.field.points
            radius = 0.46 * SHAPE[1] - STEP if cylinder else np.inf
            r = np.hypot(p[:, 1] - (SHAPE[1] - 1) / 2, p[:, 2] - (SHAPE[2] - 1) / 2)
            inside = (r < radius).reshape(item.field.shape)
            numbers = measure(
                item.error_estimate,
                truths[item.name],
                inside,
                item.error_resolution,
                windows.get(item.name),
                noise_error(item.field) if item.field.uncertainty is not None else None,
            )
            rows.append((label, item.name, numbers, item.accuracy))
        correlation = getattr(result.pair, "noise_correlation", None)
        lags = "not measured" if correlation is None else np.round(correlation.along(0), 3)
        print(
            f"{label}: r0 {result.pair.background.mean:.4g}, {seconds:.1f} s; "
            f"noise correlation at lags 1-3 along z {lags}",
            flush=True,
        )
    print(
        "| texture | field | true median | window's true median | estimated median | ratio "
        "| Spearman | caught likely / possibly (of) | false flags likely / possibly "
        "| resolution (median) | below resolution | match uncertainty (median) | p |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for label, name, m, p in rows:
        print(
            f"| {label} | {name} | {m['true_median']:.3f} | {m['window_median']:.3f} | "
            f"{m['estimated_median']:.3f} | {m['ratio']:.2f} | {m['rho']:.2f} | "
            f"{percent(m['caught'])} / {percent(m['caught_possibly'])} ({m['n_bad']}) | "
            f"{percent(m['false'])} / {percent(m['false_possibly'])} | {m['resolution']:.3f} | "
            f"{percent(m['below'])} | {_number(m['match_sigma'])} | {p:.4f} |"
        )
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--correlated", action="store_true")
    parser.add_argument(
        "--apply-correlation", action="store_true",
        help="the estimate uses the pair's measured noise correlation "
        "(noise_correlation.NOISE_CORRELATION_APPLIED)",
    )  # fmt: skip
    arguments = parser.parse_args()
    if arguments.apply_correlation:
        from napari_dvc_correct.engine.evaluation import noise_correlation

        noise_correlation.NOISE_CORRELATION_APPLIED = True
    main(arguments.quick, arguments.correlated)
