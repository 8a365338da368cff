"""Compiled loops of the EventPS relation (numba): the pairing of same-pixel events into relations as
a stream goes by, each pixel's robust fit of its exact constraints, and the refinement of a pixel
without a fit by its constraints and bounds. They run on one core and release the GIL.

Relations follow ``pstoolkit.events.rule``: the grey light at a reference time and at a later event,
and the thresholds crossed in between, so that L(t) − L(t_ref) = n⁺·C⁺ − n⁻·C⁻ (exact) or bounds it
(an event of the "rate-limited" rule fired at the end of a blind time);
``pstoolkit.events.relation.constraint_vectors`` turns them into constraints n·v = 0 or n·w ≥ 0. The
callers give the light at each event's time and at the end of its refractory period, so the loops
know nothing of light models.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pstoolkit.events.rule import TIMESTAMP_RESOLUTION_US

NO_EVENT = np.iinfo(np.int64).min
"""``last_t`` of a pixel that has not fired yet."""
RANK_ONE = 1e-12
"""Adjugate columns shorter than this share of the trace² are rounding noise of a rank-1 matrix."""
SETTLED = 1e-8
"""Reweighting stops once a pass moves the normal by less than √SETTLED (1e-4 rad, 0.006°)."""


@numba.njit(cache=True, nogil=True, error_model="numpy")
def pair_events(
    x: np.ndarray,
    y: np.ndarray,
    t_us: np.ndarray,
    polarity: np.ndarray,
    width: int,
    light: np.ndarray,
    motion: np.ndarray,
    period_us: int,
    refractory_us: int,
    rate_limited: bool,
    start_us: int,
    last_t: np.ndarray,
    anchor_t: np.ndarray,
    anchor_light: np.ndarray,
    crossed: np.ndarray,
    min_interval_us: float,
    max_interval_us: float,
    fired: np.ndarray,
    swing: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The relations of the time-ordered events (``x``, ``y``, ``t_us``, ``polarity``) of a sensor
    ``width`` pixels wide under the refractory rule (``pstoolkit.events.rule``): each gives the grey
    light at a reference time and at an event, and the thresholds crossed in between.

    The grey light (rows of ``light``) and the unit direction of the light's motion across the image
    plane (rows of ``motion``): with ``period_us`` > 0 both tabulate one period per µs, and an event at
    t reads row t mod period, its light after the refractory period row (t + refractory_us) mod period
    (the times must not decrease); with ``period_us`` = 0 they hold a row per event k, the light after
    its refractory period in row n + k.

    "reset-at-end" (``rate_limited`` false): every event and the one before it of its pixel, the
    reference at t_prev + R, one threshold of the later event's polarity. "rate-limited": consecutive
    exact events of a pixel (fired more than R + 1 µs after the pixel's previous event, or after
    ``start_us`` for its first), the reference at the earlier one's time, every threshold of the
    events after it up to the later one; and each event fired at the end of a blind time after an
    exact one, which only bounds the change since it: p·(L(t) − L(t_ref)) ≥ p·Δ (``bound`` = p; 0
    for an exact relation).

    Per-pixel state, updated so that the next call continues the stream: ``last_t`` (P,) the previous
    event (``NO_EVENT`` for none), ``anchor_t`` (P,) the time of the current reference and
    ``anchor_light`` (P, 3) the light then (``NO_EVENT``: none yet), ``crossed`` (P, 2) the positive
    and negative thresholds since it. A relation whose span lies outside [min_interval_us,
    max_interval_us] is dropped. Also counts per pixel in ``fired`` (P, 3) the events, the rising ones
    and those fired at the end of a blind time, and adds p·motion to ``swing`` (P, 2). Returns the
    relations' flat pixels y·width + x (m,), the light at the reference (m, 3) and at the later event
    (m, 3), their thresholds crossed (m, 2) (positive, negative), ``bound`` (m,) int8, in event order,
    and the number of exact relations formed before the span filter."""
    count = t_us.shape[0]
    out_pixel = np.empty(count, np.int64)
    out_ref = np.empty((count, 3))
    out_now = np.empty((count, 3))
    out_crossed = np.empty((count, 2), np.int64)
    out_bound = np.zeros(count, np.int8)
    used = 0
    pairs = 0
    exact_gap = refractory_us + TIMESTAMP_RESOLUTION_US
    # the start of the period holding the current event; times increase, so it only moves forward
    turn_start = t_us[0] - t_us[0] % period_us if period_us > 0 and count > 0 else 0
    for k in range(count):
        i = np.int64(y[k]) * width + np.int64(x[k])
        p = polarity[k]
        t = t_us[k]
        if period_us > 0:
            while t - turn_start >= period_us:
                turn_start += period_us
            now = t - turn_start
            after = now + refractory_us
            while after >= period_us:
                after -= period_us
        else:
            now, after = k, count + k
        fired[i, 0] += 1
        fired[i, 1] += 1 if p > 0 else 0
        swing[i, 0] += p * motion[now, 0]
        swing[i, 1] += p * motion[now, 1]
        crossed[i, 0 if p > 0 else 1] += 1
        previous = last_t[i]
        exact = True
        if rate_limited:
            exact = t - (start_us if previous == NO_EVENT else previous) > exact_gap
            fired[i, 2] += 0 if exact else 1
        if anchor_t[i] != NO_EVENT:
            pairs += 1 if exact else 0
            interval = t - (previous if not rate_limited else anchor_t[i])
            if min_interval_us <= interval <= max_interval_us:
                out_pixel[used] = i
                for c in range(3):
                    out_ref[used, c] = anchor_light[i, c]
                    out_now[used, c] = light[now, c]
                out_crossed[used, 0], out_crossed[used, 1] = crossed[i, 0], crossed[i, 1]
                out_bound[used] = 0 if exact else p
                used += 1
        if exact:
            anchor_t[i] = t
            reference = now if rate_limited else after
            for c in range(3):
                anchor_light[i, c] = light[reference, c]
            crossed[i, 0] = crossed[i, 1] = 0
        last_t[i] = t
    return out_pixel[:used], out_ref[:used], out_now[:used], out_crossed[:used], out_bound[:used], pairs


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _pixel_sums(u: np.ndarray, weight: np.ndarray, lo: int, hi: int, nx: float, ny: float, nz: float,
                inv_scale2: float) -> tuple[float, float, float, float, float, float]:
    """Σ a·w u uᵀ (its six unique entries) of the unit constraints ``u[lo:hi]`` with their weights a
    (``weight[lo:hi]``) and the Cauchy weight w = 1 / (1 + (n·u)² / σ²) of the residual at n (w = 1
    with ``inv_scale2`` = 0)."""
    s0 = s1 = s2 = s3 = s4 = s5 = 0.0
    for j in range(lo, hi):
        x, y, z = u[j, 0], u[j, 1], u[j, 2]
        residual = nx * x + ny * y + nz * z
        w = weight[j] / (1.0 + residual * residual * inv_scale2)
        wx, wy = w * x, w * y
        s0 += wx * x
        s1 += wx * y
        s2 += wx * z
        s3 += wy * y
        s4 += wy * z
        s5 += w * z * z
    return s0, s1, s2, s3, s4, s5


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _adjugate_steps(
    s: tuple[float, float, float, float, float, float], x: float, y: float, z: float, steps: int
) -> tuple[float, float, float]:
    """``steps`` steps of power iteration on the adjugate of the symmetric matrix ``s`` (six unique
    entries) from (x, y, z): the adjugate has the eigenvectors of the matrix with eigenvalues
    λ_j·λ_k, so the iteration converges to the smallest eigenvector at the rate λ0/λ1."""
    a, b, c, d, e, f = s
    m0, m1, m2 = d * f - e * e, c * e - b * f, b * e - c * d
    m3, m4, m5 = a * f - c * c, b * c - a * e, a * d - b * b
    for _ in range(steps):
        x, y, z = m0 * x + m1 * y + m2 * z, m1 * x + m3 * y + m4 * z, m2 * x + m4 * y + m5 * z
        length = math.sqrt(x * x + y * y + z * z)
        if length == 0:
            break
        x, y, z = x / length, y / length, z / length
    return x, y, z


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _smallest_by_adjugate(
    s: tuple[float, float, float, float, float, float], steps: int
) -> tuple[float, float, float, float, float, float]:
    """Eigenvalues (ascending) of the positive semi-definite matrix ``s`` (six unique entries) and the
    unit eigenvector of the smallest, without trigonometry: the longest column of the adjugate
    (λ1λ2·n0n0ᵀ + λ0λ2·n1n1ᵀ + λ0λ1·n2n2ᵀ, so within about λ0/λ1 of n0) refined by ``steps`` power
    steps; λ0 is the Rayleigh quotient and λ1, λ2 follow from the trace and the sum of the principal
    2×2 minors. A matrix of rank ≤ 1 has a zero adjugate (up to ``RANK_ONE`` of trace²): zero
    vector, λ0 = λ1 = 0."""
    a, b, c, d, e, f = s
    m0, m1, m2 = d * f - e * e, c * e - b * f, b * e - c * d
    m3, m4, m5 = a * f - c * c, b * c - a * e, a * d - b * b
    x, y, z = m0, m1, m2
    best = x * x + y * y + z * z
    if m1 * m1 + m3 * m3 + m4 * m4 > best:
        x, y, z = m1, m3, m4
        best = x * x + y * y + z * z
    if m2 * m2 + m4 * m4 + m5 * m5 > best:
        x, y, z = m2, m4, m5
        best = x * x + y * y + z * z
    trace = a + d + f
    if best <= (RANK_ONE * trace * trace) ** 2:
        return 0.0, 0.0, trace, 0.0, 0.0, 0.0
    length = math.sqrt(best)
    x, y, z = _adjugate_steps(s, x / length, y / length, z / length, steps)
    smallest = a * x * x + d * y * y + f * z * z + 2.0 * (b * x * y + c * x * z + e * y * z)
    rest = trace - smallest
    product = m0 + m3 + m5 - smallest * rest
    spread = math.sqrt(max(rest * rest - 4.0 * product, 0.0))
    return smallest, 0.5 * (rest - spread), 0.5 * (rest + spread), x, y, z


@numba.njit(cache=True, nogil=True, error_model="numpy")
def robust_fit(
    constraint_pixel: np.ndarray, u: np.ndarray, weight: np.ndarray, n_pixels: int, min_pairs: int, reweight: int,
    scale: float, steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's normal from its unit constraints (``constraint_pixel`` (m,), ``u`` (m, 3), weights
    ``weight`` (m,)) for pixels with at least ``min_pairs``: the smallest eigenvector of Σ a u uᵀ
    (``_smallest_by_adjugate``, a the weights), then
    up to ``reweight`` passes of iteratively reweighted least squares with Cauchy weights of scale
    ``scale`` on the residuals n·u, each moving n by ``steps`` adjugate power steps, until a pass moves
    it by less than √``SETTLED``; flipped to n_z ≥ 0. Returns normals (P, 3) (zero for the others),
    the eigenvalues (P, 3) of Σ a u uᵀ (for the rank test), its six unique entries (P, 6) (for every
    pixel with a constraint, for the neighbours) and the number of constraints per pixel (P,)."""
    m = constraint_pixel.shape[0]
    count = np.zeros(n_pixels, np.int64)
    for j in range(m):
        count[constraint_pixel[j]] += 1
    start = np.zeros(n_pixels + 1, np.int64)
    for i in range(n_pixels):
        start[i + 1] = start[i] + count[i]
    # each pixel's constraints side by side, in event order (a stable counting sort)
    grouped = np.empty((m, 3))
    grouped_weight = np.empty(m)
    fill = start[:n_pixels].copy()
    for j in range(m):
        i = constraint_pixel[j]
        grouped[fill[i], 0], grouped[fill[i], 1], grouped[fill[i], 2] = u[j, 0], u[j, 1], u[j, 2]
        grouped_weight[fill[i]] = weight[j]
        fill[i] += 1
    normal = np.zeros((n_pixels, 3))
    values = np.zeros((n_pixels, 3))
    sums = np.zeros((n_pixels, 6))
    inv_scale2 = 1.0 / (scale * scale)
    for i in range(n_pixels):
        lo, hi = start[i], start[i + 1]
        if hi == lo:
            continue
        s = _pixel_sums(grouped, grouped_weight, lo, hi, 0.0, 0.0, 0.0, 0.0)
        sums[i, 0], sums[i, 1], sums[i, 2], sums[i, 3], sums[i, 4], sums[i, 5] = s
        if hi - lo < min_pairs:
            continue
        values[i, 0], values[i, 1], values[i, 2], x, y, z = _smallest_by_adjugate(s, steps)
        for _ in range(reweight):
            nx, ny, nz = _adjugate_steps(_pixel_sums(grouped, grouped_weight, lo, hi, x, y, z, inv_scale2), x, y, z, steps)
            moved = (nx - x) ** 2 + (ny - y) ** 2 + (nz - z) ** 2
            x, y, z = nx, ny, nz
            if moved < SETTLED:
                break
        sign = -1.0 if z < 0 else 1.0
        normal[i, 0], normal[i, 1], normal[i, 2] = sign * x, sign * y, sign * z
    return normal, values, sums, count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def light_arcs(reference: np.ndarray, later: np.ndarray) -> np.ndarray:
    """(m,) angle (radians) between the light's directions at the two ends of each relation, from the
    grey lights (direction × luma) at the reference (m, 3) and at the later event (m, 3): atan2 of
    |a × b| and a·b, exact for small arcs, where arccos of a·b rounds to zero."""
    m = reference.shape[0]
    arc = np.zeros(m)
    for j in range(m):
        ax, ay, az = reference[j, 0], reference[j, 1], reference[j, 2]
        bx, by, bz = later[j, 0], later[j, 1], later[j, 2]
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        arc[j] = math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)
    return arc


@numba.njit(cache=True, nogil=True, error_model="numpy")
def capped_arc_weights(pixel: np.ndarray, arc: np.ndarray, n_pixels: int) -> np.ndarray:
    """(m,) min(1, a/ā) of each relation's arc a (``arc`` (m,)) and the mean ā of its pixel's
    (``pixel`` (m,))."""
    total = np.zeros(n_pixels)
    count = np.zeros(n_pixels)
    for j in range(pixel.shape[0]):
        total[pixel[j]] += arc[j]
        count[pixel[j]] += 1.0
    weight = np.ones(pixel.shape[0])
    for j in range(pixel.shape[0]):
        mean = total[pixel[j]] / count[pixel[j]]
        if mean > 0.0 and arc[j] < mean:
            weight[j] = arc[j] / mean
    return weight


@numba.njit(cache=True, nogil=True, error_model="numpy")
def bounded_fit(
    normal: np.ndarray,
    todo: np.ndarray,
    exact_pixel: np.ndarray,
    u: np.ndarray,
    exact_weight: np.ndarray,
    bound_pixel: np.ndarray,
    w: np.ndarray,
    prior: float,
    passes: int,
    scale: float,
) -> None:
    """Refines the normals (P, 3) of the pixels ``todo`` (k,) in place with their own constraints:
    exact ones n·u = 0 (``exact_pixel`` (m,), unit ``u`` (m, 3), weights a ``exact_weight`` (m,)) and
    one-sided ones n·w ≥ 0 (``bound_pixel`` (b,), unit ``w`` (b, 3)). Each pass takes the smallest
    eigenvector of Σ a·c u uᵀ + Σ c w wᵀ over the violated w + ``prior``·(I − n₀n₀ᵀ), n₀ the starting normal (the
    squared hinge, with a pull to the start where the constraints leave n free), with Cauchy weights
    c = 1 / (1 + r²/``scale``²) of the residuals r at the current normal (a noise event breaks the
    relations after it until the next exact event), for at most ``passes`` passes or until a pass
    moves the normal by less than √``SETTLED``; flipped to n_z ≥ 0.
    Pixel arrays must be sorted (as ``pair_events`` gives them after a stable sort by pixel)."""
    exact_start = np.searchsorted(exact_pixel, todo)
    exact_end = np.searchsorted(exact_pixel, todo, side="right")
    bound_start = np.searchsorted(bound_pixel, todo)
    bound_end = np.searchsorted(bound_pixel, todo, side="right")
    inv_scale2 = 1.0 / (scale * scale)
    for k in range(todo.shape[0]):
        i = todo[k]
        if bound_end[k] == bound_start[k]:
            continue
        x0, y0, z0 = normal[i, 0], normal[i, 1], normal[i, 2]
        x, y, z = x0, y0, z0
        for _ in range(passes):
            e = _pixel_sums(u, exact_weight, exact_start[k], exact_end[k], x, y, z, inv_scale2)
            s0 = e[0] + prior * (1.0 - x0 * x0)
            s1 = e[1] - prior * x0 * y0
            s2 = e[2] - prior * x0 * z0
            s3 = e[3] + prior * (1.0 - y0 * y0)
            s4 = e[4] - prior * y0 * z0
            s5 = e[5] + prior * (1.0 - z0 * z0)
            for j in range(bound_start[k], bound_end[k]):
                a, b, c = w[j, 0], w[j, 1], w[j, 2]
                residual = a * x + b * y + c * z
                if residual < 0.0:
                    weight = 1.0 / (1.0 + residual * residual * inv_scale2)
                    s0 += weight * a * a
                    s1 += weight * a * b
                    s2 += weight * a * c
                    s3 += weight * b * b
                    s4 += weight * b * c
                    s5 += weight * c * c
            _, _, _, nx, ny, nz = _smallest_by_adjugate((s0, s1, s2, s3, s4, s5), 8)
            if nx == 0.0 and ny == 0.0 and nz == 0.0:
                break
            if nz < 0:
                nx, ny, nz = -nx, -ny, -nz
            moved = (nx - x) ** 2 + (ny - y) ** 2 + (nz - z) ** 2
            x, y, z = nx, ny, nz
            if moved < SETTLED:
                break
        normal[i, 0], normal[i, 1], normal[i, 2] = x, y, z
