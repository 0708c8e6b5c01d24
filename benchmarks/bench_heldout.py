"""Held-out cases: textures, fields and warps nobody tuned a constant on (docs/heldout.md).

The cases of ``bench_correction_cases.py`` and ``bench_real.py`` are what the engine's constants
were tuned on. These are not: other textures, other fields, and deformed scans made with **another
interpolator** than ours (``scipy.ndimage.map_coordinates`` of order 1 or 5, or a Fourier shift;
never our cubic B-spline).

Textures (100³ cut from a pattern 16 voxels larger on every side, so material that enters the
view is the pattern's continuation; gray values on an 8-bit-like range 0-255):

* ``weak``: two phases 7 % of the range apart (100 / 118), grains of 3-6 voxels, a faint texture
  of 2 gray levels inside the phases;
* ``cylinder``: a two-phase specimen (90 / 170) in a cylinder along z of radius 40 in dark air (20),
  only the nodes whose centre is inside radius 40 - 4 counted;
* ``foam``: thin walls (about 1.5 voxels, gray 200) around cells of about 10 voxels (gray 40):
  mostly empty;
* ``rock``: the real intact rock scan (``../shared/data/real-rock/rock_upper.npz``, reference,
  read-only) as the pattern: a 132³ crop of it, its offset chosen by the seed;
* ``rocksm``: the same crop smoothed over 1 voxel (Gaussian): the scan's own noise and finest
  pores gone, a poor texture (std 3.0 gray levels against 5.9 for the crop of seed 1; a 3 %
  noise is 7.7).

Noise (added to both scans, independent draws): ``gN``: Gaussian of N % of the range (255);
``pN``: Poisson-like, variance proportional to the gray value, N % of the range at the
specimen's mean gray.

Fields (about the volume's centre; z, y, x voxels):

* ``rotD``: rigid rotation by D degrees about an inclined axis (0.9, 0.3, 0.3), with a small
  translation;
* ``compP``: uniaxial compression of P % along z with barrelling (radial expansion
  ``0.3 P r (1 + 0.6 (1 - (2 (z - c) / N)²))``: largest at mid-height);
* ``bandW-S``: a shear band of full width W voxels (tanh half-width W / 2), offset S voxels,
  plane normal (1, 0, 1);
* ``crackD``: a crack opening D voxels: a plane (normal (1, 0.3, 0), through the centre) whose
  two sides move apart by D along the normal (a jump), the gap filled with the air's gray (the
  ``rock``'s 1st percentile); nodes within 8 voxels of the plane (0.8 of the subvolume's
  half-width) are the truly bad ones;
* ``shift``: a translation (1.3, -2.6, 0.7).

Warps: ``o1`` / ``o5``: the deformed scan ``F(x) = G(X(x))`` with ``X(x)`` the exact inverse of
the field (closed form for rotation, shift and crack, fixed-point iteration otherwise) sampled by
``map_coordinates`` of that order; ``fft``: a Fourier shift (translation only).

Per case: the plain RMSE and the corrected RMSE against the true field on the measured nodes
(not ``MASKED``, a finite value) inside the specimen, the share of those nodes flagged (not a good
status) after the correction, the share of **truly bad** nodes (the nodes near the crack;
elsewhere none: a node that is more than 0.5 voxel off after the correction is counted as
"> 0.5 off"), the nodes the correction harmed (more than 0.1 voxel worse than plain; "good
harmed": of those, nodes with a good status after the correction), and the wall time of the plain
run and of the correction. DVC: subvolume 21, step 8, first order, no mask (as ``bench_peers``).

Run: ``python benchmarks/bench_heldout.py [--seed N] [--list] [case ...]`` (a case is
``texture/field/warp/noise``, e.g. ``rock/rot10/o1/g2``). The machine is shared: compare seconds
within one run only. Experiments (not the product's behaviour): ``--pass-method 1,21`` or
``2,15,3.5`` forces the correcting matches' order, subvolume and Gaussian window (``-``: none)
instead of :func:`.pass_method.pass_method`'s choice; ``--noise-fit`` runs the correction with
``noise_fit=True``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction import self_correction
from napari_dvc_correct.engine.correction.self_correction import correct
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import GOOD_STATUSES, Status

N = 100
MARGIN = 16
CENTER = (N - 1) / 2.0
PARAMS = CorrelationParams(subvolume=21, step=8)
RANGE = 255.0
ROCK = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-rock" / "rock_upper.npz"

CASES = [
    "rock/shift/fft/g1",
    "rock/shift/o5/g3",
    "rocksm/shift/o5/g3",
    "rock/rot3/o5/g2",
    "rock/rot10/o1/g2",
    "rock/band8-2/o5/p3",
    "rock/crack2/o5/g2",
    "weak/comp3/o5/g3",
    "weak/band6-2/o1/p4",
    "weak/crack1/o1/g6",
    "cylinder/comp5/o5/p3",
    "cylinder/rot6/o1/g2",
    "cylinder/crack1.5/o5/g3",
    "foam/band4-3/o5/g2",
    "foam/rot5/o5/g1",
    "foam/comp2/o1/g4",
    "rock/band12-1/o1/p6",
]


# --- textures: pattern(shape, seed) -> (volume, inside(points) or None, air gray) ---------------
def weak_texture(shape, seed):
    volume = synthetic.two_phase_volume(
        shape, grain_size=1.5, phase_grays=(100.0, 118.0), texture=2.0, seed=seed
    )
    return volume, None, 20.0


def cylinder_texture(shape, seed):
    material = synthetic.two_phase_volume(
        shape, grain_size=1.5, phase_grays=(90.0, 170.0), texture=6.0, seed=seed
    )
    y, x = np.indices(shape[1:], dtype=np.float64)
    radius = np.hypot(y - (shape[1] - 1) / 2.0, x - (shape[2] - 1) / 2.0)
    # soft edge about one voxel wide
    inside = 1.0 / (1.0 + np.exp(-(40.0 - radius) / 0.5))
    volume = 20.0 + (material - 20.0) * inside[None]
    return (
        volume.astype(np.float32),
        lambda p: np.hypot(p[:, 1] - CENTER, p[:, 2] - CENTER) < 36,
        20.0,
    )


def foam_texture(shape, seed):
    rng = np.random.default_rng(seed)
    field = ndimage.gaussian_filter(rng.standard_normal(shape), 3.0, mode="wrap")
    field /= field.std()
    # walls where the smooth field crosses zero: |field| / |grad field| is the distance to the
    # level set; a Gaussian profile of that distance gives walls about 1.5 voxels thick
    gradient = np.sqrt(sum(g**2 for g in np.gradient(field)))
    distance = np.abs(field) / np.maximum(gradient, 1e-6)
    wall = np.exp(-0.5 * (distance / 0.75) ** 2)
    return (40.0 + 160.0 * wall).astype(np.float32), None, 40.0


def rock_texture(shape, seed):
    if not ROCK.exists():
        raise FileNotFoundError(f"{ROCK} is absent (a clone without ../shared)")
    scan = np.load(ROCK)["reference"]
    room = np.array(scan.shape) - np.array(shape)
    offset = np.random.default_rng(seed).integers(0, room + 1)
    crop = tuple(slice(o, o + n) for o, n in zip(offset, shape))
    volume = scan[crop].astype(np.float32)
    return volume, None, float(np.percentile(scan, 1.0))


def rock_smooth_texture(shape, seed):
    volume, inside, air = rock_texture(shape, seed)
    return ndimage.gaussian_filter(volume, 1.0), inside, air


TEXTURES = {
    "weak": weak_texture, "cylinder": cylinder_texture, "foam": foam_texture, "rock": rock_texture,
    "rocksm": rock_smooth_texture,
}  # fmt: skip


# --- fields: (u(X), inverse X(x) or None, gap(x) or None, straddles(points) or None) -------------
def rotation(degrees, axis=(0.9, 0.3, 0.3), shift=(0.4, -0.7, 0.3)):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    angle = np.deg2rad(degrees)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    shift, center = np.asarray(shift), np.full(3, CENTER)
    forward = lambda p: (np.asarray(p) - center) @ rot.T + center + shift - p  # noqa: E731
    inverse = lambda x: (np.asarray(x) - center - shift) @ rot + center  # noqa: E731
    return forward, inverse, None, None


def compression(percent, poisson=0.3, barrel=0.6):
    strain = percent / 100.0

    def u(points):
        p = np.asarray(points, np.float64) - CENTER
        height = 2.0 * p[:, 0] / N
        radial = poisson * strain * (1.0 + barrel * (1.0 - height**2))
        return np.column_stack([-strain * p[:, 0], radial * p[:, 1], radial * p[:, 2]])

    return u, None, None, None


def band(width, offset):
    u = synthetic.shear_band((CENTER,) * 3, width=width / 2.0, slip=offset, shift=(0.3, 0.5, -0.4))
    return u, None, None, None


def crack(opening, normal=(1.0, 0.3, 0.0), shift=(0.5, -0.8, 0.6)):
    normal = np.asarray(normal) / np.linalg.norm(normal)
    shift = np.asarray(shift)

    def side(points):
        return (np.asarray(points, np.float64) - CENTER) @ normal

    def u(points):
        return shift + 0.5 * opening * np.sign(side(points))[:, None] * normal

    def inverse(x):
        d = side(np.asarray(x) - shift)
        return x - shift - 0.5 * opening * np.sign(d)[:, None] * normal

    def gap(x):
        return np.abs(side(np.asarray(x) - shift)) < 0.5 * opening

    def straddles(points):
        # the plane passes within 0.8 of a subvolume's half-width of the node: plain errors
        # 0.4-0.8 voxel there, 0.03-0.06 beyond (rock/crack2/o5/g2, seed 1)
        return np.abs(side(points)) < 0.8 * (PARAMS.subvolume // 2)

    return u, inverse, gap, straddles


def make_field(name: str):
    if name == "shift":
        shift = np.array([1.3, -2.6, 0.7])
        return synthetic.translation(shift), lambda x: x - shift, None, None
    if name.startswith("rot"):
        return rotation(float(name[3:]))
    if name.startswith("comp"):
        return compression(float(name[4:]))
    if name.startswith("band"):
        width, offset = (float(v) for v in name[4:].split("-"))
        return band(width, offset)
    if name.startswith("crack"):
        return crack(float(name[5:]))
    raise ValueError(f"unknown field {name!r}")


# --- warps ------------------------------------------------------------------------------------
def warp(big, field, warp_name, air):
    """The deformed pattern ``F(x) = G(X(x))`` (big volume coordinates: the field is given in
    the cropped ones)."""
    u, inverse, gap, _ = field
    if warp_name == "fft":
        shift = u(np.zeros((1, 3)))[0]
        spectrum = ndimage.fourier_shift(np.fft.fftn(big.astype(np.float64)), shift)
        return np.fft.ifftn(spectrum).real.astype(np.float32)
    order = int(warp_name[1:])
    x = np.indices(big.shape, dtype=np.float64).reshape(3, -1).T - MARGIN
    if inverse is not None:
        source = inverse(x)
    else:
        source = synthetic.invert_displacement(u, x)
    out = ndimage.map_coordinates(
        big.astype(np.float64), (source + MARGIN).T, order=order, mode="mirror"
    )
    if gap is not None:
        out[gap(x)] = air
    return out.reshape(big.shape).astype(np.float32)


def add_noise(volume, kind: str, mean_gray: float, seed: int):
    percent = float(kind[1:]) / 100.0
    rng = np.random.default_rng(seed)
    sigma = percent * RANGE
    if kind[0] == "g":
        return (volume + rng.normal(0.0, sigma, volume.shape)).astype(np.float32)
    # Poisson-like: variance proportional to the gray value, sigma at the mean gray
    scale = np.sqrt(np.maximum(volume, 0.0) / mean_gray)
    return (volume + sigma * scale * rng.standard_normal(volume.shape)).astype(np.float32)


def make_case(case: str, seed: int = 1):
    """``(reference, deformed, truth u(X), inside(points) or None, straddles or None)``."""
    texture, field_name, warp_name, noise = case.split("/")
    shape = (N + 2 * MARGIN,) * 3
    big, inside, air = TEXTURES[texture](shape, seed)
    field = make_field(field_name)
    deformed_big = warp(big, field, warp_name, air)
    crop = (slice(MARGIN, MARGIN + N),) * 3
    reference, deformed = big[crop], deformed_big[crop]
    mean_gray = float(np.mean(reference if inside is None else reference[reference > air + 10]))
    reference = add_noise(reference, noise, mean_gray, seed=10 * seed + 1)
    deformed = add_noise(deformed, noise, mean_gray, seed=10 * seed + 2)
    return (
        np.ascontiguousarray(reference),
        np.ascontiguousarray(deformed),
        field[0],
        inside,
        field[3],
    )


CHOSEN_PASS_METHOD = self_correction.pass_method


def force_pass_method(spec: str | None) -> None:
    """Make the correction match with ``order,subvolume[,window]`` (None: its own choice)."""
    if spec is None:
        self_correction.pass_method = CHOSEN_PASS_METHOD
        return
    order, subvolume, *rest = spec.split(",")
    window = None if not rest or rest[0] in ("", "-") else float(rest[0])

    def forced(field, params, exclude=None):
        return params.replace(order=int(order), subvolume=int(subvolume), window=window), (
            f"forced by bench_heldout --pass-method {spec}"
        )

    self_correction.pass_method = forced


def run(case: str, seed: int, noise_fit: bool = False) -> dict:
    reference, deformed, truth, inside, straddles = make_case(case, seed)
    started = time.perf_counter()
    plain = correlate(reference, deformed, PARAMS)
    plain_s = time.perf_counter() - started
    started = time.perf_counter()
    corrected = correct(reference, deformed, plain, PARAMS, noise_fit=noise_fit)
    correction_s = time.perf_counter() - started
    points = plain.points
    expected = truth(points)
    before = np.linalg.norm(plain.displacement - expected, axis=1)
    after = np.linalg.norm(corrected.displacement - expected, axis=1)
    status = corrected.status.reshape(-1)
    measured = plain.status.reshape(-1) != int(Status.MASKED)
    select = measured & (True if inside is None else inside(points))
    bad = np.zeros(len(points), bool) if straddles is None else straddles(points)
    good = np.isin(status, [int(s) for s in GOOD_STATUSES])
    plain_good = np.isin(plain.status.reshape(-1), [int(s) for s in GOOD_STATUSES])

    def rmse(errors, where):
        ok = where & np.isfinite(errors)
        return float(np.sqrt(np.mean(errors[ok] ** 2))) if ok.any() else float("nan")

    harmed = select & np.isfinite(before) & (np.nan_to_num(after, nan=np.inf) > before + 0.1)
    row = {
        "case": case,
        "nodes": int(select.sum()),
        "plain": rmse(before, select),
        "corrected": rmse(after, select),
        "plain_ok": rmse(before, select & ~bad),
        "corrected_ok": rmse(after, select & ~bad),
        "plain_flagged": float(np.mean(~plain_good[select])),
        "flagged": float(np.mean(~good[select])),
        "truly_bad": float(np.mean(bad[select])),
        "flagged_bad": float(np.mean(~good[select & bad]))
        if (select & bad).any()
        else float("nan"),
        "flagged_ok": float(np.mean(~good[select & ~bad])),
        "discontinuity": int(np.sum(status[select] == int(Status.DISCONTINUITY))),
        "off": int(np.sum(select & ~bad & (after > 0.5))),
        "off_good": int(np.sum(select & ~bad & (after > 0.5) & good)),
        "harmed": int(harmed.sum()),
        "good_harmed": int(np.sum(harmed & good & ~bad)),
        "plain_s": plain_s,
        "correction_s": correction_s,
        "passes": len(corrected.metadata.get("correction_passes", [])) - 1,
        "stop": corrected.metadata["correction"].get("stop_reason", ""),
    }
    return row


HEADER = (
    "| case | nodes | plain RMSE | corrected RMSE | off the crack: plain / corrected | flagged "
    "plain / corrected | truly bad | flagged of bad / of the rest | DISCONT. | >0.5 off (good) | "
    "harmed (good) | passes | plain s | correction s |\n" + "|---" * 14 + "|"
)


def line(row: dict) -> str:
    bad = f"{row['truly_bad']:.0%}" if row["truly_bad"] else "—"
    of_bad = f"{row['flagged_bad']:.0%}" if np.isfinite(row["flagged_bad"]) else "—"
    return (
        f"| {row['case']} | {row['nodes']} | {row['plain']:.3f} | {row['corrected']:.3f} | "
        f"{row['plain_ok']:.3f} / {row['corrected_ok']:.3f} | {row['plain_flagged']:.1%} / "
        f"{row['flagged']:.1%} | {bad} | {of_bad} / {row['flagged_ok']:.1%} | "
        f"{row['discontinuity']} | {row['off']} ({row['off_good']}) | {row['harmed']} "
        f"({row['good_harmed']}) | {row['passes']} | {row['plain_s']:.1f} | "
        f"{row['correction_s']:.1f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("cases", nargs="*", help="texture/field/warp/noise; default: the list")
    parser.add_argument("--seed", type=int, default=1, help="texture, crop and noise seed")
    parser.add_argument("--list", action="store_true", help="print the default cases and stop")
    parser.add_argument(
        "--pass-method",
        metavar="ORDER,SUBVOLUME[,WINDOW]",
        help="experiment: force the correcting matches' parameters (e.g. 1,21 or 2,15,3.5)",
    )
    parser.add_argument(
        "--noise-fit", action="store_true", help="experiment: correct with noise_fit=True"
    )
    args = parser.parse_args()
    if args.list:
        print("\n".join(CASES))
        return
    force_pass_method(args.pass_method)
    print(HEADER, flush=True)
    for case in args.cases or CASES:
        print(line(run(case, args.seed, args.noise_fit)), flush=True)


if __name__ == "__main__":
    main()
