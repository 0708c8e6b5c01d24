"""Local DVC: ``correlate(G, F, params) -> DisplacementField``.

The pipeline, coarse to fine:

1. prefilter ``F`` into B-spline coefficients and compute the gradient of ``G`` (once per volume);
2. estimate the rigid shift of the whole specimen (phase correlation of binned volumes);
3. on a binned pyramid (when the search radius exceeds a few voxels), search every POI's integer
   displacement by FFT cross-correlation at the coarsest level and refine it with IC-GN level by
   level;
4. run IC-GN at full resolution for every POI in parallel, in batches that report progress;
5. reliability-guided repair: POIs that failed, matched poorly or disagree with their neighbours are
   matched again from the warps of their best converged neighbours, best first.
"""

from __future__ import annotations

import time
from collections.abc import Generator

import numpy as np

from ..backend import select_device
from ..fields.field import GOOD_STATUSES, DisplacementField, Status, grid_for_volume
from ..progress import Progress, run_to_completion
from ..validation import validate_volume
from . import shape_function
from .guided_repair import repair, search_seeds, seed_guesses
from .initial_guess import global_shift, pyramid_levels
from .match_judgement import MatchedGrid, judge_iter
from .noise import NOISE_GRADIENT_GAIN, SENSITIVITY_FRACTION, noise_estimates
from .params import CorrelationParams
from .pyramid import PyramidLevel, build_level
from .pyramid_rule import level_reach

_GOOD = np.array([int(s) for s in GOOD_STATUSES])


#: Integer dtypes whose every value float32 holds exactly: volumes of one of these are not copied
#: to float32 by :func:`match_iter` (its kernels read them as they are, with the same values).
EXACT_IN_FLOAT32 = (np.uint8, np.int8, np.uint16, np.int16)

#: ... from this many voxels (64 MiB as float32): below, the copy costs less than loading the
#: prefilter's kernel for one more dtype at start-up.
KEEP_INTEGER_FROM = 2**24


def validate_pair(
    reference,
    deformed,
    params: CorrelationParams,
    mask=None,
    *,
    exact_deformed=False,
    exact_reference=False,
):
    """Check the inputs of a correlation; return float32 volumes and a boolean mask (or None).

    ``exact_deformed`` / ``exact_reference``: a deformed / reference volume of 8- or 16-bit
    integers of at least :data:`KEEP_INTEGER_FROM` voxels is returned as it is (C order) rather
    than as a float32 copy (every value is exact in float32; saves a volume of memory).

    Raises
    ------
    ValueError
        With a message that says what to change: not 3-D, shapes that differ, NaN or infinite
        values, a subvolume larger than the volume, an empty mask or a mask of another shape.
    """
    reference = validate_volume(reference, "reference volume")
    deformed = validate_volume(deformed, "deformed volume")
    if reference.shape != deformed.shape:
        raise ValueError(
            f"reference {reference.shape} and deformed {deformed.shape} volumes must have the "
            "same shape"
        )
    if params.subvolume > min(reference.shape):
        from ..pair_checks import largest_subvolume_advice

        raise ValueError(
            f"subvolume {params.subvolume} is larger than the volume {reference.shape}: "
            + largest_subvolume_advice(reference.shape)
        )
    reference = _float32_or_exact(reference, exact_reference)
    deformed = _float32_or_exact(deformed, exact_deformed)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != reference.shape:
            raise ValueError(f"mask shape {mask.shape} differs from the volume {reference.shape}")
        if mask.dtype.kind == "f" and not np.all(np.isfinite(mask)):  # NaN != 0 is "material"
            raise ValueError(
                "the mask contains NaN or infinite values: use 0 = outside, 1 = material"
            )
        mask = np.ascontiguousarray(mask != 0)
        if not mask.any():
            raise ValueError("the mask is empty: no voxel is selected")
    return reference, deformed, mask


def _float32_or_exact(volume, exact: bool) -> np.ndarray:
    """``volume`` as C-ordered float32, or as it is where ``exact`` allows (see
    :func:`validate_pair`)."""
    if exact and kept_as_integers(volume):
        return np.ascontiguousarray(volume)
    return np.ascontiguousarray(volume, dtype=np.float32)


def kept_as_integers(volume) -> bool:
    """Whether a CPU correlation reads ``volume`` as it is rather than as a float32 copy: 8- or
    16-bit integers (every value exact in float32) of at least :data:`KEEP_INTEGER_FROM`
    voxels."""
    volume = np.asanyarray(volume)
    return volume.dtype.type in EXACT_IN_FLOAT32 and volume.size >= KEEP_INTEGER_FROM


def _grid_centers(grid, volume_shape, half):
    origin, step, shape = grid
    axes = [np.asarray(origin[a]) + np.asarray(step[a]) * np.arange(shape[a]) for a in range(3)]
    zz, yy, xx = np.meshgrid(*axes, indexing="ij")
    points = np.stack([zz.ravel(), yy.ravel(), xx.ravel()], axis=1)
    centers = np.rint(points).astype(np.int64)
    if np.max(np.abs(points - centers), initial=0.0) > 1e-6:
        raise ValueError("POI positions (origin + i * step) must be whole voxels")
    inside = np.all((centers >= half) & (centers <= np.array(volume_shape) - 1 - half), axis=1)
    return centers, inside


def correlate_seeds(
    reference,
    deformed,
    params: CorrelationParams,
    centers,
    *,
    levels: int,
    rigid_shift,
    mask=None,
    texture_std=None,
    device="cpu",
):
    """The seeds of :func:`correlate_iter`'s initial guess, matched at ``centers`` alone.

    What :func:`.guided_repair.seed_guesses` computes for its seeds at the coarsest of
    ``levels`` pyramid levels: FFT search within the level's radius around ``rigid_shift``, then
    IC-GN (:func:`.guided_repair.search_seeds`). For :mod:`.tiled`'s seed pass, on a region
    of the volumes.

    Parameters
    ----------
    reference, deformed, mask, texture_std, device
        As for :func:`correlate_iter` (volumes may be a region of the whole ones).
    centers : ndarray of int, shape (S, 3)
        Seed POI centres, voxels of ``reference``.
    levels : int
        Pyramid levels of the whole volume.
    rigid_shift : array-like of 3 ints
        The whole volume's rigid shift (voxels).

    Returns
    -------
    params : ndarray, shape (S, 3·nb)
        Shape-function parameters at the coarsest level (its voxels).
    zncc, status : ndarray, shape (S,)
    level_centers : ndarray of int, shape (S, 3)
        The seeds' centres at that level, in its voxels of ``reference``.
    """
    device = select_device(device)
    reference, deformed, mask = validate_pair(reference, deformed, params, mask)
    level = build_level(levels, reference, deformed, mask, params, device.kind, texture_std)
    level_centers = level.centers_from_fine(np.asarray(centers, np.int64).reshape(-1, 3))
    shift = np.rint(np.asarray(rigid_shift, np.float64)).astype(np.int64).reshape(3)
    reach = level_reach(params, levels)
    seed_params, zncc, status = search_seeds(
        level, level_centers, shift / reach.factor, reach.search_radius, params.order, params
    )
    return seed_params, zncc, status, level_centers


def match_iter(
    reference: np.ndarray,
    deformed: np.ndarray,
    params: CorrelationParams | None = None,
    *,
    mask: np.ndarray | None = None,
    grid: tuple | None = None,
    initial: DisplacementField | None = None,
    rigid_shift=None,
    device="cpu",
    texture_std=None,
    grid_anchor=None,
    seeds=None,
    active=None,
    prefiltered=None,
    noise_hint=None,
    weights=None,
) -> Generator[Progress, None, tuple[MatchedGrid, PyramidLevel]]:
    """The first half of :func:`correlate_iter` (same parameters): the POIs matched, not judged.

    Prefilter, initial guess, each POI's subvolume moments (the noise estimate's ingredients) and
    full-resolution IC-GN; :func:`.match_judgement.judge_iter` does the rest. :mod:`..tiled`
    runs the two halves as separate tasks, with the whole run's noise estimate in between.

    Returns
    -------
    matched : judge.MatchedGrid
    fine : PyramidLevel
        The full-resolution level (the volumes' prefilter and gradient), for the judge's repair.
    """
    params = CorrelationParams() if params is None else params
    device = select_device(device)
    start_time = time.perf_counter()
    timings = {}
    # the GPU's kernels read a float32 reference; the CPU's read integers as they are
    reference, deformed, mask = validate_pair(
        reference, deformed, params, mask, exact_deformed=True,
        exact_reference=device.kind == "cpu",
    )  # fmt: skip
    if grid is None:
        grid = grid_for_volume(reference.shape, params.subvolume, params.step)
    origin, step, grid_shape = grid
    grid_shape = tuple(int(n) for n in grid_shape)
    if min(grid_shape) < 1:
        raise ValueError(f"the POI grid is empty (shape {grid_shape})")
    half = level_reach(params, 0).half
    centers, inside = _grid_centers(grid, reference.shape, half)
    n_points = len(centers)
    order = params.order
    nb = shape_function.n_monomials(order)
    if initial is not None and initial.shape != grid_shape:
        raise ValueError(
            f"initial field grid {initial.shape} differs from the POI grid {grid_shape}"
        )

    def build_fine():
        yield Progress("prefilter", 0, 1, "prefiltering the volumes")
        started = time.perf_counter()
        level = PyramidLevel.build(
            1,
            reference,
            deformed,
            mask,
            half,
            params.min_texture,
            device.kind,
            std=None if texture_std is None else texture_std[1],
            prefiltered=prefiltered,
            weights=params.subvolume_weights() if weights is None else weights,
        )
        timings["prefilter_s"] = time.perf_counter() - started
        yield Progress("prefilter", 1, 1, "volumes prefiltered")
        return level

    radius = params.effective_search_radius
    timings["prefilter_s"] = 0.0
    # with a pyramid, the full-resolution level (∇G, F's coefficients: five volumes) is built
    # after the coarse levels are done with, so that the two never take memory together
    fine = None
    if (
        initial is not None
        or seeds is None
        and (pyramid_levels(radius, params.subvolume, reference.shape) == 0)
    ):
        fine = yield from build_fine()

    built_early = fine is not None
    t0 = time.perf_counter()
    if initial is not None:
        guess_params = shape_function.displacement_to_params(
            initial.displacement,
            None if initial.gradient is None else initial.gradient.reshape(-1, 3, 3),
            order,
        )
        shift = np.zeros(3, np.int64)
        levels = 0
    else:
        yield Progress("initial guess", 0, 1, "estimating the rigid shift")
        shift = (
            global_shift(reference, deformed)
            if rigid_shift is None
            else np.rint(np.asarray(rigid_shift, np.float64)).astype(np.int64).reshape(3)
        )
        levels = (
            pyramid_levels(radius, params.subvolume, reference.shape)
            if seeds is None
            else int(seeds.levels)
        )
        guess_params = None
        guess_counts = {}
        for lev in range(levels, -1, -1):
            if lev == 0 and fine is None:
                level = None  # the coarse level's memory is free before the fine one is built
                fine = yield from build_fine()
            level = (
                fine
                if lev == 0
                else build_level(lev, reference, deformed, mask, params, device.kind, texture_std)
            )
            level_centers = level.centers_from_fine(centers)
            if guess_params is None:
                reach = level_reach(params, lev)
                guess_params = seed_guesses(
                    level,
                    level_centers,
                    grid_shape,
                    shift / reach.factor,
                    reach.search_radius,
                    order,
                    params,
                    anchor=grid_anchor,
                    seeds=seeds,
                )
                yield Progress("initial guess", 1, levels + 2, f"seeds matched (level {lev})")
            if lev == 0:
                break
            before = guess_params.copy()
            zncc_l, status_l, its_l = level.match(level_centers, guess_params, order, params)
            repair(
                level,
                level_centers,
                grid_shape,
                guess_params,
                zncc_l,
                status_l,
                its_l,
                order,
                params,
                counts=guess_counts,
            )
            failed = ~np.isin(status_l, _GOOD)
            guess_params[failed] = before[failed]  # keep the carried guess where matching failed
            shaped = guess_params.reshape(-1, 3, nb)
            shaped[:, :, 0] *= 2.0  # displacement in the next finer voxels
            if nb == 10:
                shaped[:, :, 4:] /= 2.0  # second derivatives scale with 1 / factor
            yield Progress("initial guess", levels - lev + 2, levels + 2, f"level {lev} refined")
        for name, value in guess_counts.items():
            timings[f"{name}_guess"] = value
    if fine is None:  # seeds=GivenSeeds with no level
        fine = yield from build_fine()
    timings["initial_guess_s"] = (
        time.perf_counter() - t0 - (0.0 if built_early else timings["prefilter_s"])
    )

    # full-resolution IC-GN in batches
    t0 = time.perf_counter()
    params_out = np.ascontiguousarray(guess_params, dtype=np.float64)
    zncc = np.full(n_points, np.nan)
    status = np.full(n_points, int(Status.OUT_OF_BOUNDS), np.int64)
    iterations = np.zeros(n_points, np.int64)
    # the uncertainty from each match's own reference terms (the judge then measures again
    # only the POIs that need the sensitivity pass or were repaired)
    sigma = np.full((n_points, 3), np.nan)
    sigma_plain = np.zeros(n_points, bool)
    sigma_sensitive = np.zeros(n_points, bool)
    todo = np.flatnonzero(inside)
    if active is not None:
        chosen = np.asarray(active, bool).reshape(-1)
        todo = todo[chosen[todo]]
        status[~chosen] = int(Status.NOT_COMPUTED)
    # the noise estimates' ingredients (variance and gradient power): from the reference alone, so
    # measured before IC-GN, for the noise hint of a first sample of POIs
    t_noise = time.perf_counter()
    variance = np.full(n_points, np.nan)
    power = np.full(n_points, np.nan)
    fine.moments(centers[todo], order, (variance, power), todo)
    noise_seconds = time.perf_counter() - t_noise
    batch = params.batch_size
    # without a hint, the first batch is a sample spread over the grid (every k-th POI) and
    # the rest take the hint of its median noise estimate, as the judge estimates the noise
    sampled = noise_hint is None and device.kind == "cpu" and len(todo) > batch
    if sampled:
        first = np.zeros(len(todo), bool)
        first[:: -(-len(todo) // batch)] = True
        todo_order = np.concatenate([todo[first], todo[~first]])
    else:
        todo_order = todo
    # POIs expected noisy at the hinted noise get the sensitivity pass in the same kernel call
    # (the judge's rule, match_judgement.judge_iter, with the hint for the run's noise)
    noise_power = 0.0 if noise_hint is None else _noise_power(noise_hint)
    for start in range(0, len(todo_order), batch):
        index = todo_order[start : start + batch]
        sub_params = np.ascontiguousarray(params_out[index])
        sub_sigma = np.zeros((len(index), 4))
        z_b, s_b, i_b = fine.match(
            centers[index], sub_params, order, params, sigma=sub_sigma, noise_power=noise_power
        )
        plain = sub_sigma[:, 3] == 1.0
        sensitive = sub_sigma[:, 3] == 2.0
        sigma[index[plain | sensitive]] = sub_sigma[plain | sensitive, :3]
        sigma_plain[index[plain]] = True
        sigma_sensitive[index[sensitive]] = True
        params_out[index] = sub_params
        zncc[index] = z_b
        status[index] = s_b
        iterations[index] = i_b
        if sampled and start == 0:
            estimates = noise_estimates(variance[index], z_b, s_b)
            if estimates.size:
                noise_power = _noise_power(float(np.median(estimates)))
        yield Progress(
            "IC-GN",
            min(start + batch, len(todo)),
            len(todo),
            f"matched {min(start + batch, len(todo))} of {len(todo)} POIs",
        )
    timings["icgn_s"] = time.perf_counter() - t0 - noise_seconds
    timings["voxel_iterations"] = int(iterations.sum()) * params.subvolume**3
    timings["noise_s"] = noise_seconds
    matched = MatchedGrid(
        grid=(origin, step, grid_shape),
        centers=centers,
        todo=todo,
        params=params_out,
        zncc=zncc,
        status=status,
        iterations=iterations,
        variance=variance,
        power=power,
        sigma=sigma,
        sigma_plain=sigma_plain,
        sigma_sensitive=sigma_sensitive,
        metadata={
            "volume_shape": list(reference.shape),
            "global_shift": [int(s) for s in shift],
            "pyramid_levels": int(levels),
            "timings": timings,
            "masked": mask is not None,
            "device": device.description,
        },
        started=start_time,
    )
    return matched, fine


def _noise_power(noise_variance: float) -> float:
    """The gradient power (gray²/voxel²) below which a POI is noisy at ``noise_variance``
    (the judge's rule, :func:`.match_judgement.judge_iter`), for IC-GN's kernel."""
    return 3.0 * NOISE_GRADIENT_GAIN * float(noise_variance) / SENSITIVITY_FRACTION


def correlate_iter(
    reference: np.ndarray,
    deformed: np.ndarray,
    params: CorrelationParams | None = None,
    *,
    mask: np.ndarray | None = None,
    grid: tuple | None = None,
    initial: DisplacementField | None = None,
    rigid_shift=None,
    device="cpu",
    texture_std=None,
    grid_anchor=None,
    seeds=None,
    active=None,
    prefiltered=None,
    noise_hint=None,
    weights=None,
) -> Generator[Progress, None, DisplacementField]:
    """Correlate ``reference`` (G) with ``deformed`` (F), yielding progress; returns the field.

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        The two volumes, any real dtype (processed as float32). Axis order (z, y, x).
    params : CorrelationParams, optional
        Subvolume, step, shape-function order, search radius... (defaults if None).
    mask : ndarray of bool, shape (nz, ny, nx), optional
        Reference-space mask of the material: only voxels inside it enter the matching, and POIs
        with less than ``params.min_mask_fraction`` of their subvolume inside get ``MASKED``.
    grid : (origin, step, shape), optional
        POI grid in reference voxels; whole-voxel positions. Default:
        :func:`grid_for_volume` ``(shape, subvolume, step)``.
    initial : DisplacementField, optional
        Initial guess on the same grid (skips the global and FFT searches).
    rigid_shift : array-like of 3 ints, optional
        Rigid shift ``(z, y, x)`` voxels to search around instead of estimating it from these
        volumes: the whole volume's shift when they are a region of larger volumes
        (:mod:`.tiled`).
    texture_std : mapping of int to float, optional
        Gray standard deviation of the whole reference volume (inside the mask) binned by each
        pyramid factor ``1, 2, 4...``, for the low-texture test, when these volumes are a region
        of larger ones (:mod:`.tiled`). Default: computed from these volumes.
    grid_anchor : (offset, whole_shape), optional
        When ``grid`` is a box of a larger POI grid (a batch of :mod:`.tiled`): the whole-grid
        index ``(z, y, x)`` of its first POI and the whole grid's shape, so that the seeds of the
        initial guess are the whole grid's (:func:`.guided_repair.seed_axes`) and the batch
        computes what the in-memory run computes for its POIs. Default: ``grid`` is the whole
        grid.
    seeds : guided_repair.GivenSeeds, optional
        The seeds of the initial guess, matched and judged on the whole grid (:mod:`.tiled`'s
        seed pass): every POI starts from its nearest good seed of the whole grid, as in memory,
        and the pyramid has the whole volume's ``seeds.levels``. Default: seeds searched here.
    active : ndarray of bool, shape of the grid, optional
        Match only these POIs (the self-correction's selective passes, :mod:`.self_correction`); the
        others get ``Status.NOT_COMPUTED`` and NaN, and take no part in the noise estimate, the
        thresholds or the repair. Default: every POI.
    prefiltered : Prefiltered, optional
        ``∇G`` and/or ``F``'s coefficients already computed for exactly these volumes (the
        self-correction's unchanged volume, computed once for all passes). Default: computed.
    noise_hint : float, optional
        The imaging noise variance (gray levels²) expected of this pair, e.g. from an earlier
        run on the same scans: the POIs that are noisy at it get the sensitivity pass of their
        uncertainty in the IC-GN kernel's call, from the terms IC-GN holds, instead of in a
        second pass over their subvolumes. It changes no result: the judge still decides each
        POI's noisiness at the run's own noise and measures again where the hint guessed wrong.
        0: no POI is expected noisy. Default: on the CPU, the median noise estimate of a first
        batch of POIs spread over the grid (:func:`.noise.noise_estimates`, as the judge
        estimates the run's noise), for the other POIs.
    weights : ndarray, shape (subvolume,)*3, optional
        Weights of the subvolume's voxels (any non-negative weights, e.g. an oriented window
        of :mod:`..correction.oriented`) instead of ``params.subvolume_weights()``: the weighted
        IC-GN (:mod:`.icgn_weighted`, on the CPU). Default: those of ``params.window``.
    device : {"cpu", "cuda", "auto"} or backend.Device
        Where IC-GN runs (:func:`.backend.select_device`; a missing GPU falls back to the CPU with
        a warning). The field's ``metadata["device"]`` says which was used.

    Yields
    ------
    Progress
        One report per stage and per batch of POIs.

    Returns
    -------
    DisplacementField
        ``u`` in voxels at each POI, with ``zncc``, ``status``, ``iterations`` and the shape
        function's displacement ``gradient``.
    """
    params = CorrelationParams() if params is None else params
    matched, fine = yield from match_iter(
        reference,
        deformed,
        params,
        mask=mask,
        grid=grid,
        initial=initial,
        rigid_shift=rigid_shift,
        device=device,
        texture_std=texture_std,
        grid_anchor=grid_anchor,
        seeds=seeds,
        active=active,
        prefiltered=prefiltered,
        noise_hint=noise_hint,
        weights=weights,
    )
    field, _ = yield from judge_iter(matched, fine, params)
    return field


# correlate repeats correlate_iter's signature (the duplicate finder pairs them): the blocking
# form of the generator keeps the same keywords, spelt out so that help() shows them.
def correlate(
    reference: np.ndarray,
    deformed: np.ndarray,
    params: CorrelationParams | None = None,
    *,
    mask: np.ndarray | None = None,
    grid: tuple | None = None,
    initial: DisplacementField | None = None,
    rigid_shift=None,
    device="cpu",
    texture_std=None,
    grid_anchor=None,
    seeds=None,
    active=None,
    prefiltered=None,
    noise_hint=None,
    weights=None,
) -> DisplacementField:
    """Blocking form of :func:`correlate_iter` (same parameters, no progress)."""
    return run_to_completion(
        correlate_iter(
            reference,
            deformed,
            params,
            mask=mask,
            grid=grid,
            initial=initial,
            rigid_shift=rigid_shift,
            device=device,
            texture_std=texture_std,
            grid_anchor=grid_anchor,
            seeds=seeds,
            active=active,
            prefiltered=prefiltered,
            noise_hint=noise_hint,
            weights=weights,
        )
    )
