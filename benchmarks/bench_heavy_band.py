"""The heavy-noise narrow band: where its error sits, and regularised estimates measured against it.

``narrow_heavy`` of :mod:`bench_correction_cases` (two-phase texture, a narrow inclined band of
half-width 4 with rotation, translation and bending, noise 0.8 x the texture's std on both scans;
subvolume 21, step 6). Errors in voxels against the truth at the 343 nodes, RMSE over all nodes
and by the node's distance from the band's mid-plane (0-3, 3-6, 6-10, 10-15, > 15 voxels).

1. **Split**: the same texture without noise (``narrow_clean``, same seed) gives the first run's
   bias (plain clean - truth) and its noise (plain heavy - plain clean).
2. **TGV on the node field**: the plain field denoised by a vectorial second-order total
   generalised variation (Chambolle-Pock / Condat-Vu primal-dual), data term weighted by each
   node's uncertainty, weight chosen by the discrepancy principle (chi2 = number of data).
3. **Regularised passes**: ``D <- TGV(D + c)``, ``c`` a first-order 21³ correcting match on the
   pulled-back scan, for a few passes.
4. **Band-oriented windows** (``oriented``): the match's subvolume weighted by an anisotropic
   Gaussian, narrow across the band's TRUE plane and wide along it (an oracle orientation), in
   the plain run on the plain field's grid and in every correcting pass of the self-correction
   (first or second order, the pass method overridden); tilting the plane by 10-20° shows what
   an orientation estimated from the data would lose.
5. **Global DVC**: a trilinear mesh (element 4 voxels) over the subvolumes' support fitted to the
   images by Gauss-Newton (reference gradient, affine gray-level line), regularised by the
   squared second differences of the nodes (bending), by their Huber-reweighted norm (keeps
   kinks), or anisotropically: strongly along the plane of least curvature of the Huber run's
   field (from the data), or along the band's TRUE plane (an oracle).

The regularisation weights of 3. and 4. were chosen against the truth on seed 4 and are used
unchanged on other seeds, so they show what is possible, not what a data-driven choice would
give. Results and discussion: docs/method.md ("The heavy-noise narrow
band: regularised estimates, measured").

6. **Deblur** (``deblur``): the self-correction's own oriented step split into bias and scatter:
   its re-match (planes from the data, the step's windows) from the field the passes leave, on
   the heavy pair and on the noise-free pair (``narrow_clean``, same start and planes), raw and
   after :func:`~.oriented_deblur.deblur_across`; ``--stds A B``: other stds (voxels).

7. **Deblur speed** (``deblur_speed``, alone): :func:`~.oriented_deblur.deblur_across` on
   synthetic grids of 7³, 15³ and 25³ nodes, step 6 (a noisy band, the step's window of std 2 /
   12 on a 31³ box, every node matched), process CPU seconds (``time.process_time``: run it
   with ``NUMBA_NUM_THREADS=1``) per node, best of ``--repeats`` (default 3) after a warm-up;
   the nodes deblurred and a checksum of the values, to compare two versions of the code.

Run: ``python benchmarks/bench_heavy_band.py [--seed N] [--case NAME] [part ...]`` (parts: split
tgv passes oriented global deblur deblur_speed; default all but deblur and deblur_speed; seed default 4; case default narrow_heavy, any case of
:mod:`bench_correction_cases` with a band: the zones are distances from its mid-plane; "split"
needs narrow_heavy).
"""

from __future__ import annotations

import contextlib
import itertools
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from scipy import ndimage
from scipy.interpolate import RegularGridInterpolator

sys.path.insert(0, str(Path(__file__).parent))
from bench_correction_cases import CENTER, make_case  # noqa: E402

from napari_dvc_correct.engine.correction import oriented, self_correction  # noqa: E402
from napari_dvc_correct.engine.correction.pass_update import zero_start  # noqa: E402
from napari_dvc_correct.engine.correction.self_correction import correct  # noqa: E402
from napari_dvc_correct.engine.correlation.correlate import correlate  # noqa: E402
from napari_dvc_correct.engine.correlation.params import CorrelationParams  # noqa: E402
from napari_dvc_correct.engine.fields.field import GOOD_STATUSES  # noqa: E402
from napari_dvc_correct.engine.fields.warp import pull_back  # noqa: E402
from napari_dvc_correct.engine.progress import run_to_completion  # noqa: E402

ZONES = [(0, 3), (3, 6), (6, 10), (10, 15), (15, 1e9)]
NORMAL = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)  # the band's mid-plane (points' axes)


def zone_row(
    name: str, error: np.ndarray, distance: np.ndarray, note: str = "", nodes=None
) -> None:
    """A table row: RMSE over the nodes (``nodes``: a boolean grid of those to count, default
    every node with a finite error; fewer than all is said in the note) and per zone."""
    e = np.linalg.norm(error, axis=-1)
    if nodes is None:
        nodes = np.isfinite(e)
    if not nodes.all():
        note = f"{note}; {int(nodes.sum())} of {nodes.size} nodes".lstrip("; ")
    e = np.where(nodes, e, np.nan)
    values = [np.sqrt(np.nanmean(e**2))]
    values += [np.sqrt(np.nanmean(e[(distance >= a) & (distance < b)] ** 2)) for a, b in ZONES]
    print(f"| {name:<44} | " + " | ".join(f"{v:.3f}" for v in values) + f" | {note} |", flush=True)


# --- vectorial TGV² on a regular grid (fields of shape (nz, ny, nx, 3)) ----------------------
def _grad(v, h):
    g = np.zeros(v.shape + (3,))
    for a in range(3):
        index = [slice(None)] * v.ndim
        index[a] = slice(0, -1)
        g[tuple(index) + (a,)] = np.diff(v, axis=a) / h
    return g


def _div(g, h):  # minus the adjoint of _grad
    out = np.zeros(g.shape[:-1])
    for a in range(3):
        p = g[..., a]
        d = np.zeros_like(p)
        at = lambda s: tuple([slice(None)] * a + [s])  # noqa: E731, B023
        d[at(slice(0, 1))] = p[at(slice(0, 1))]
        d[at(slice(1, -1))] = p[at(slice(1, -1))] - p[at(slice(0, -2))]
        d[at(slice(-1, None))] = -p[at(slice(-2, -1))]
        out += d / h
    return out


def _sym_grad(w, h):  # backward differences, symmetrised
    g = np.zeros(w.shape + (3,))
    for a in range(3):
        d = np.zeros_like(w)
        at = lambda s: tuple([slice(None)] * a + [s])  # noqa: E731, B023
        d[at(slice(0, 1))] = w[at(slice(0, 1))]
        d[at(slice(1, -1))] = w[at(slice(1, -1))] - w[at(slice(0, -2))]
        d[at(slice(-1, None))] = -w[at(slice(-2, -1))]
        g[..., a] = d / h
    return 0.5 * (g + np.swapaxes(g, -1, -2))


def _sym_div(q, h):  # minus the adjoint of _sym_grad
    q = 0.5 * (q + np.swapaxes(q, -1, -2))
    out = np.zeros(q.shape[:-1])
    for a in range(3):
        p, m = q[..., a], q.shape[a]
        t = np.zeros_like(p)
        at = lambda s: tuple([slice(None)] * a + [s])  # noqa: E731, B023
        t[at(slice(0, 1))] += p[at(slice(0, 1))]
        t[at(slice(1, m - 1))] += p[at(slice(1, m - 1))]
        t[at(slice(0, m - 2))] -= p[at(slice(1, m - 1))]
        t[at(slice(m - 2, m - 1))] -= p[at(slice(m - 1, m))]
        out -= t / h
    return out


def _project(p, alpha, axes):
    norm = np.sqrt(np.sum(p * p, axis=axes, keepdims=True))
    return p / np.maximum(1.0, norm / alpha)


def _operator_norm2(shape, h):
    rng = np.random.default_rng(1)
    v, w = rng.standard_normal(shape + (3,)), rng.standard_normal(shape + (3, 3))
    for _ in range(40):
        p = _grad(v, h) - w
        v2, w2 = -_div(p, h), -p - _sym_div(_sym_grad(w, h), h)
        norm = np.sqrt(np.sum(v2**2) + np.sum(w2**2))
        v, w = v2 / norm, w2 / norm
    return 1.05 * norm


def tgv_denoise(data, weight, h, alpha1, iterations=2000):
    """``argmin ½ Σ weight (v - data)² + α1 |∇v - w| + 2 h α1 |E w|`` (Condat-Vu)."""
    alpha0 = 2.0 * h * alpha1
    shape = data.shape[:3]
    v, w = data.copy(), np.zeros(shape + (3, 3))
    p, q = np.zeros_like(w), np.zeros(shape + (3, 3, 3))
    k2 = _operator_norm2(shape, h)
    sigma = 1.0 / np.sqrt(k2)
    tau = 0.99 / (np.max(weight) / 2 + sigma * k2)
    for _ in range(iterations):
        vn = v - tau * (weight * (v - data) - _div(p, h))
        wn = w - tau * (-p - _sym_div(q, h))
        vb, wb = 2 * vn - v, 2 * wn - w
        p = _project(p + sigma * (_grad(vb, h) - wb), alpha1, (-2, -1))
        q = _project(q + sigma * _sym_grad(wb, h), alpha0, (-3, -2, -1))
        v, w = vn, wn
    return v


def node_weights(field):
    good = np.isin(field.status, [int(g) for g in GOOD_STATUSES])
    good &= np.all(np.isfinite(field.uncertainty) & (field.uncertainty > 0), axis=-1)
    sigma = np.where(good[..., None], field.uncertainty, 1.0)
    weight = np.where(good[..., None], 1.0 / sigma**2, 0.0)
    scale = float(np.median(weight[weight > 0]))
    return weight / scale, scale, int(good.sum())


def discrepancy_tgv(data, weight, scale, good, h):
    """TGV with α1 bisected (log) so that Σ (v - data)² / σ² = 3 x the good nodes."""
    low, high = 1e-3, 10.0
    for _ in range(12):
        alpha = np.sqrt(low * high)
        v = tgv_denoise(data, weight, h, alpha, 1500)
        chi2 = np.sum(weight * (v - data) ** 2) * scale
        low, high = (alpha, high) if chi2 <= 3 * good else (low, alpha)
    return v, alpha, chi2 / (3 * good)


# --- global DVC on a trilinear mesh ------------------------------------------------------------
class GlobalDvc:
    """Gauss-Newton on ``Σ_X (a F(X + u(X)) + b - G(X))²`` over the subvolumes' support, ``u``
    trilinear on a mesh of element ``element`` voxels, plus a quadratic regulariser."""

    def __init__(self, reference, deformed, field, element=4.0):
        points = field.points.reshape(-1, 3)
        low, high = points.min(0) - field_half(field), points.max(0) + field_half(field)
        self.origin, self.element = low, float(element)
        self.nodes = np.ceil((high - low) / element).astype(int) + 1
        axes = [np.arange(int(np.ceil(low[a])), int(np.floor(high[a])) + 1) for a in range(3)]
        voxels = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        self.voxels = voxels.astype(np.float64)
        self.phi = self.shape_matrix(self.voxels)
        self.at_nodes = self.shape_matrix(points)
        reference = np.asarray(reference, np.float64)
        self.g = reference[tuple(voxels.T)]
        self.gradient = np.stack(np.gradient(reference), -1)[tuple(voxels.T)]
        self.coefficients = ndimage.spline_filter(np.asarray(deformed, np.float64), order=3)
        self.hessian = sp.bmat(
            [
                [self.phi.T @ sp.diags(self.gradient[:, a] * self.gradient[:, b]) @ self.phi
                 for b in range(3)]
                for a in range(3)
            ]
        ).tocsr()  # fmt: skip
        self.scale = float(np.var(reference))
        self.start = self.from_field(field)
        # the pair's mismatch at the start (noise of both scans, and the start's error) after an
        # affine gray-level line: a penalty scaled by it fades where the images are clean
        at = self.voxels + np.stack([self.phi @ self.start[:, c] for c in range(3)], -1)
        moved = ndimage.map_coordinates(
            self.coefficients, at.T, order=3, prefilter=False, mode="nearest"
        )
        contrast, offset = np.polyfit(moved, self.g, 1)
        self.mismatch = float(np.mean((self.g - contrast * moved - offset) ** 2))

    def shape_matrix(self, points):
        t = (points - self.origin) / self.element
        i0 = np.clip(np.floor(t).astype(int), 0, self.nodes - 2)
        f = t - i0
        rows, cols, values = [], [], []
        for corner in itertools.product((0, 1), repeat=3):
            o = np.array(corner)
            rows.append(np.arange(len(points)))
            cols.append(np.ravel_multi_index(tuple((i0 + o).T), self.nodes))
            values.append(np.prod(np.where(o, f, 1 - f), axis=1))
        return sp.csr_matrix(
            (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
            shape=(len(points), int(np.prod(self.nodes))),
        )

    def from_field(self, field):
        axes = [field.origin[a] + field.step[a] * np.arange(field.shape[a]) for a in range(3)]
        mesh = np.stack(
            np.meshgrid(
                *[self.origin[a] + self.element * np.arange(self.nodes[a]) for a in range(3)],
                indexing="ij",
            ),
            -1,
        ).reshape(-1, 3)
        mesh = np.clip(mesh, [a[0] for a in axes], [a[-1] for a in axes])
        u = np.nan_to_num(field.u)
        return np.stack([RegularGridInterpolator(axes, u[..., c])(mesh) for c in range(3)], -1)

    def second_differences(self, offset):
        index = np.arange(int(np.prod(self.nodes))).reshape(self.nodes)
        nodes = np.argwhere(np.ones(self.nodes, bool))
        o = np.asarray(offset)
        inside = np.all((nodes - o >= 0) & (nodes - o < self.nodes), axis=1)
        inside &= np.all((nodes + o >= 0) & (nodes + o < self.nodes), axis=1)
        c = nodes[inside]
        rows = np.tile(np.arange(len(c)), 3)
        cols = np.concatenate([index[tuple((c - o).T)], index[tuple(c.T)], index[tuple((c + o).T)]])
        values = np.concatenate([np.ones(len(c)), -2 * np.ones(len(c)), np.ones(len(c))])
        return sp.csr_matrix((values, (rows, cols)), shape=(len(c), index.size))

    def solve(self, regulariser, weight, huber=0.0, iterations=8, on_mesh=False):
        """``regulariser``: a sparse second-difference operator; ``huber`` > 0 reweights its rows
        by ``min(1, huber / |row|)`` each iteration (an L1-like penalty that keeps kinks).
        Returns the field at the DVC nodes, or at the mesh's nodes (``on_mesh``)."""
        u = self.start.copy()
        penalty = sp.block_diag([regulariser.T @ regulariser] * 3).tocsr()
        for _ in range(iterations):
            if huber > 0:
                rows = np.stack([regulariser @ u[:, c] for c in range(3)], -1)
                w = np.minimum(1.0, huber / np.maximum(np.linalg.norm(rows, axis=-1), 1e-12))
                penalty = sp.block_diag([regulariser.T @ sp.diags(w) @ regulariser] * 3).tocsr()
            at = self.voxels + np.stack([self.phi @ u[:, c] for c in range(3)], -1)
            moved = ndimage.map_coordinates(
                self.coefficients, at.T, order=3, prefilter=False, mode="nearest"
            )
            contrast, offset = np.polyfit(moved, self.g, 1)
            residual = self.g - (contrast * moved + offset)
            rhs = np.concatenate([self.phi.T @ (self.gradient[:, c] * residual) for c in range(3)])
            rhs = rhs / contrast - weight * self.scale * (penalty @ u.T.reshape(-1))
            step, _ = spl.cg(self.hessian + weight * self.scale * penalty, rhs, rtol=1e-6)
            u = u + step.reshape(3, -1).T
        return u if on_mesh else np.stack([self.at_nodes @ u[:, c] for c in range(3)], -1)

    def along_structure(self, u, smoothing=2.0):
        """Second derivatives along the plane of least curvature at each interior mesh node: its
        normal is the first eigenvector of ``Σ_k H_k H_kᵀ`` (``H_k`` the Hessian of component
        ``k`` of ``u``, smoothed over one element; the tensor over ``smoothing`` elements)."""
        nodes = tuple(int(n) for n in self.nodes)
        u = u.reshape(nodes + (3,))
        tensor = np.zeros(nodes + (3, 3))
        for k in range(3):
            g = np.stack(np.gradient(ndimage.gaussian_filter(u[..., k], 1.0)), -1)
            hessian = np.stack([np.stack(np.gradient(g[..., a]), -1) for a in range(3)], -2)
            tensor += np.einsum("...ab,...cb->...ac", hessian, hessian)
        tensor = ndimage.gaussian_filter(tensor, (smoothing,) * 3 + (0, 0))
        normal = np.linalg.eigh(tensor)[1][..., -1]
        helper = np.where(np.abs(normal[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        first = np.cross(normal, helper)
        first /= np.linalg.norm(first, axis=-1, keepdims=True)
        tangents = (first, np.cross(normal, first))
        index = np.arange(int(np.prod(nodes))).reshape(nodes)
        inner = np.argwhere(np.ones(nodes, bool))
        inner = inner[np.all((inner >= 1) & (inner < np.array(nodes) - 1), axis=1)]
        eye = np.eye(3, dtype=int)
        rows, cols, values = [], [], []
        for number, tangent in enumerate(tangents):
            t = tangent[tuple(inner.T)]
            row = number * len(inner) + np.arange(len(inner))
            for a, b in itertools.product(range(3), repeat=2):
                if a == b:
                    stencil = ((-eye[a], 1.0), (0 * eye[a], -2.0), (eye[a], 1.0))
                else:
                    stencil = tuple(
                        (sa * eye[a] + sb * eye[b], 0.25 * sa * sb)
                        for sa, sb in itertools.product((1, -1), repeat=2)
                    )
                for offset, coefficient in stencil:
                    rows.append(row)
                    cols.append(index[tuple((inner + offset).T)])
                    values.append(coefficient * t[:, a] * t[:, b])
        return sp.csr_matrix(
            (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
            shape=(2 * len(inner), index.size),
        )


def oriented_window(half: int, normal, across: float, along: float) -> np.ndarray:
    """Weights ``(2·half + 1)³`` of an anisotropic Gaussian: std ``across`` voxels along
    ``normal`` (z, y, x), ``along`` in the plane normal to it."""
    r = np.arange(-half, half + 1, dtype=np.float64)
    z, y, x = np.meshgrid(r, r, r, indexing="ij")
    t = z * normal[0] + y * normal[1] + x * normal[2]
    plane = z * z + y * y + x * x - t * t
    return np.exp(-t * t / (2.0 * across**2) - plane / (2.0 * along**2))


@contextlib.contextmanager
def oriented_matches(normal, across, along, order=None, subvolume=None):
    """Every weighted match uses :func:`oriented_window` (its ``window`` only switches the
    weights on); with ``order`` / ``subvolume`` the self-correction's passes are forced to them
    (first or second order, that box, the oriented weights) instead of its pass method."""
    original = CorrelationParams.subvolume_weights
    method = self_correction.pass_method

    def weights(params):
        if params.window is None:
            return None
        return oriented_window(params.half, normal, across, along)

    def forced(field, params):
        return params.replace(order=order, subvolume=subvolume, window=1.0), "oriented (forced)"

    CorrelationParams.subvolume_weights = weights
    if order is not None:
        self_correction.pass_method = forced
    try:
        yield
    finally:
        CorrelationParams.subvolume_weights = original
        self_correction.pass_method = method


def tilted(normal, degrees: float) -> np.ndarray:
    """``normal`` turned by ``degrees`` about the y axis."""
    angle = np.radians(degrees)
    axis = np.array([0.0, 1.0, 0.0])
    return normal * np.cos(angle) + np.cross(axis, normal) * np.sin(angle)


def field_half(field) -> int:
    return int(field.params.get("subvolume", 21)) // 2


def deblur_split(reference, deformed, plain, params, target, distance, seed, stds=None) -> None:
    """The oriented step's re-match and its deblur, on the heavy and the noise-free pair."""
    captured = {}
    step = self_correction.oriented_step

    def spy(volumes, judge, current, *rest):
        captured["current"] = current.copy()
        return (yield from step(volumes, judge, current, *rest))

    self_correction.oriented_step = spy
    try:
        corrected = correct(reference, deformed, plain)
    finally:
        self_correction.oriented_step = step
    zone_row("corrected (default, with the step)", corrected.u - target, distance)
    current = captured["current"]
    good = np.isin(current.status, [int(s) for s in GOOD_STATUSES])
    normals, planarity, _ = oriented.plane_normals(current, usable=good)
    nodes = good & (planarity >= oriented.PLANARITY)
    nodes &= oriented.border_room(current, reference.shape) >= params.half
    clean_pair = make_case("narrow_clean", seed)[:2]
    saved = oriented.ACROSS_FRACTION, oriented.ALONG_FRACTION
    if stds is not None:
        oriented.ACROSS_FRACTION, oriented.ALONG_FRACTION = (v / params.half for v in stds)
    try:
        runs = {}
        for name, pair in (("heavy", (reference, deformed)), ("clean", clean_pair)):
            matched, oriented_runs = run_to_completion(
                oriented.oriented_rematch(
                    oriented.ArrayMatcher(*pair), current, nodes, normals, params
                )
            )
            took = nodes & np.all(np.isfinite(matched.u), axis=-1)
            deblurred, _ = oriented.deblur_matches(matched, took, oriented_runs, normals)
            runs[name] = matched.u, deblurred, took
    finally:
        oriented.ACROSS_FRACTION, oriented.ALONG_FRACTION = saved
    _, across, along = oriented.oriented_params(params)
    both = runs["heavy"][2] & runs["clean"][2]
    for index, label in ((0, "re-match"), (1, "deblurred")):
        heavy, clean = runs["heavy"][index], runs["clean"][index]
        name = f"{label} (std {across:g} / {along:g})"
        zone_row(name, heavy - target, distance, "", both)
        zone_row(f"  {label}: bias (noise-free pair)", clean - target, distance, "", both)
        zone_row(f"  {label}: scatter (heavy - noise-free)", heavy - clean, distance, "", both)


def deblur_speed(repeats: int = 3, sizes=(7, 15, 25)) -> None:
    """CPU seconds per node of the deblur on synthetic grids (see the module's part 7)."""
    from napari_dvc_correct.engine.correction import oriented_deblur

    params = CorrelationParams(subvolume=21, step=6)
    _, across, along = oriented.oriented_params(params)
    half = oriented.oriented_params(params)[0].half
    window = oriented.oriented_window(half, NORMAL, across, along)
    rng = np.random.default_rng(0)

    def case(n):
        axes = [10.0 + 6.0 * np.arange(n)] * 3
        points = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
        t = (points - points.reshape(-1, 3).mean(0)) @ NORMAL
        u = np.stack([1.4 * np.tanh(t / 4.0), 0.001 * t**2, 0.3 + 0.02 * t], -1)
        u += rng.normal(0.0, 0.1, u.shape)
        moments = np.broadcast_to(oriented_deblur.window_moments(window), (n, n, n, 3, 3))
        nodes, normals = np.ones((n,) * 3, bool), np.broadcast_to(NORMAL, points.shape)
        return u, points, nodes, normals, moments, 6.0, along

    oriented_deblur.deblur_across(*case(5))  # warm-up (compilation or cache load)
    print(f"| grid | nodes | deblurred | CPU s (best of {repeats}) | ms per node | checksum |")
    print("|---|---|---|---|---|---|")
    for n in sizes:
        arguments = case(n)
        best = np.inf
        for _ in range(repeats):
            started = time.process_time()
            deblurred, taken = oriented_deblur.deblur_across(*arguments)
            best = min(best, time.process_time() - started)
        checksum = float(np.sum(deblurred[taken]))
        print(
            f"| {n}³ | {n**3} | {int(taken.sum())} | {best:.3f} | {1e3 * best / n**3:.4f} | "
            f"{checksum:.15g} |",
            flush=True,
        )


# --- the parts ---------------------------------------------------------------------------------
def main(parts, seed: int, case: str = "narrow_heavy", stds=None) -> None:
    reference, deformed, truth, params, _ = make_case(case, seed)
    plain = correlate(reference, deformed, params)
    points = plain.points.reshape(-1, 3)
    distance = np.abs((points - CENTER) @ NORMAL).reshape(plain.shape)
    target = truth(points).reshape(plain.u.shape)
    print(
        f"seed {seed}; nodes per zone {[int(((distance >= a) & (distance < b)).sum()) for a, b in ZONES]}"
    )
    print("| estimate | all | 0-3 | 3-6 | 6-10 | 10-15 | > 15 | note |")
    print("|---|---|---|---|---|---|---|---|")
    zone_row("plain (first order 21³)", plain.u - target, distance)
    if "split" in parts:
        corrected = correct(reference, deformed, plain)
        zone_row("corrected (default)", corrected.u - target, distance)
        ref_c, def_c, _, _, _ = make_case("narrow_clean", seed)
        clean = correlate(ref_c, def_c, params)
        zone_row("  bias: plain without noise - truth", clean.u - target, distance)
        zone_row("  noise: plain - plain without noise", plain.u - clean.u, distance)
        clean_corrected = correct(ref_c, def_c, clean)
        zone_row("  corrected without noise - truth", clean_corrected.u - target, distance)
    weight, scale, good = node_weights(plain)
    h = float(plain.step[0])
    if "tgv" in parts:
        started = time.perf_counter()
        v, alpha, chi2 = discrepancy_tgv(np.nan_to_num(plain.u), weight, scale, good, h)
        note = f"α1 {alpha:.3g}, chi2/N {chi2:.2f}, {time.perf_counter() - started:.0f} s"
        zone_row("TGV of the plain nodes, discrepancy", v - target, distance, note)
    if "passes" in parts:
        grid = (plain.origin, plain.step, plain.shape)
        current = plain.copy()
        fill = float(np.mean(deformed))
        for number in range(1, 5):
            moved = pull_back(deformed, current, cval=fill)
            change = correlate(reference, moved, params, grid=grid, initial=zero_start(grid))
            weight_c, _, _ = node_weights(change)
            current = current.copy()
            current.u = tgv_denoise(current.u + np.nan_to_num(change.u), weight_c, h, 1.0)
            zone_row(f"TGV (α1 = 1) after first-order pass {number}", current.u - target, distance)
    if "oriented" in parts:
        grid = (plain.origin, plain.step, plain.shape)
        for box, across, along, tilt in (
            (31, 2.5, 10.0, 0),
            (31, 2.5, 10.0, 10),
            (31, 2.0, 12.0, 0),
        ):
            with oriented_matches(tilted(NORMAL, tilt), across, along):
                started = time.perf_counter()
                field = correlate(
                    reference, deformed, params.replace(subvolume=box, window=1.0), grid=grid
                )
            name = f"plain, oriented {box}³ (std {across} across, {along} along), tilt {tilt}°"
            note = f"{time.perf_counter() - started:.0f} s; oracle plane"
            matched = np.all(np.isfinite(field.u), axis=-1)
            zone_row(
                "  plain (first order 21³) on its nodes", plain.u - target, distance, "", matched
            )
            zone_row(name, field.u - target, distance, note)
        if "split" not in parts:
            zone_row(
                "corrected (default)", correct(reference, deformed, plain).u - target, distance
            )
        for order, box, across, along in (
            (1, 31, 2.5, 10.0),
            (1, 31, 2.0, 12.0),
            (1, 25, 2.0, 9.0),
            (2, 31, 2.5, 10.0),
        ):
            with oriented_matches(NORMAL, across, along, order, box):
                started = time.perf_counter()
                corrected = correct(reference, deformed, plain)
            name = f"corrected, oriented passes order {order} {box}³ (std {across} / {along})"
            note = f"{time.perf_counter() - started:.0f} s; oracle plane"
            zone_row(name, corrected.u - target, distance, note)
    if "deblur" in parts:
        deblur_split(reference, deformed, plain, params, target, distance, seed, stds)
    if "global" in parts:
        mesh = GlobalDvc(reference, deformed, plain)
        bending = sp.vstack(
            [mesh.second_differences(o) for o in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]
        ).tocsr()
        along = sp.vstack([mesh.second_differences(o) for o in ((0, 1, 0), (1, 0, -1))]).tocsr()
        runs = [
            ("bending, λ 3", bending, 3.0, 0.0),
            ("bending, λ 10", bending, 10.0, 0.0),
            ("bending Huber 0.01, λ 100", bending, 100.0, 0.01),
        ]
        for name, regulariser, weight_r, huber in runs:
            started = time.perf_counter()
            estimate = mesh.solve(regulariser, weight_r, huber, 12 if huber else 8)
            note = f"{time.perf_counter() - started:.0f} s"
            zone_row(f"global DVC, {name}", estimate.reshape(target.shape) - target, distance, note)
        # the band's plane from the data: the Huber run's curvature, then 1000x along it
        first = mesh.solve(bending, 100.0, 0.01, 12, on_mesh=True)
        combined = sp.vstack([bending, np.sqrt(1000.0) * mesh.along_structure(first)]).tocsr()
        estimate = mesh.solve(combined, 0.1, 0.0, 8)
        name = "global DVC, λ 0.1 + 1000x along the field's own plane"
        zone_row(name, estimate.reshape(target.shape) - target, distance, "plane from the data")
        # the same with every weight scaled by the start's mismatch instead of the texture's
        # variance (0.128 = 0.1 / 0.78, 0.78 = the mismatch over the variance this was tuned at)
        mesh.scale = mesh.mismatch
        first = mesh.solve(bending, 128.0, 0.01, 12, on_mesh=True)
        combined = sp.vstack([bending, np.sqrt(1000.0) * mesh.along_structure(first)]).tocsr()
        estimate = mesh.solve(combined, 0.128, 0.0, 8)
        name = "the same, weights x the start's mismatch"
        note = f"mismatch / var(G) {mesh.mismatch / float(np.var(reference)):.3f}"
        zone_row(name, estimate.reshape(target.shape) - target, distance, note)
        mesh.scale = float(np.var(reference))
        for across, strength in ((0.3, 100.0), (0.1, 1000.0)):
            combined = sp.vstack([bending, np.sqrt(strength) * along]).tocsr()
            estimate = mesh.solve(combined, across, 0.0, 8)
            name = f"global DVC, λ {across} + {strength:g}x along the TRUE plane"
            zone_row(name, estimate.reshape(target.shape) - target, distance, "oracle")


if __name__ == "__main__":
    arguments = sys.argv[1:]
    chosen_seed = 4
    if arguments[:1] == ["--seed"]:
        chosen_seed, arguments = int(arguments[1]), arguments[2:]
    chosen_case = "narrow_heavy"
    if arguments[:1] == ["--case"]:
        chosen_case, arguments = arguments[1], arguments[2:]
    chosen_stds = None
    if arguments[:1] == ["--stds"]:
        chosen_stds, arguments = (float(arguments[1]), float(arguments[2])), arguments[3:]
    if arguments[:1] == ["--repeats"]:
        chosen_repeats, arguments = int(arguments[1]), arguments[2:]
    else:
        chosen_repeats = 3
    if arguments == ["deblur_speed"]:
        deblur_speed(chosen_repeats)
        sys.exit(0)
    main(
        arguments or ["split", "tgv", "passes", "oriented", "global"],
        chosen_seed, chosen_case, chosen_stds,
    )  # fmt: skip
