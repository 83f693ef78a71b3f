"""Edge tracking (paper Sec. IV-C): event clusters on the 8 static edges of the white ring drive
asynchronous pose updates.

Each event (ideal pixel coordinates) joins every edge within the gate; an edge is cut into
``alpha * length`` bins that each keep their newest event, so a cluster stays spread along its
edge. An edge's latency indicator is the mean distance of its cluster; when more than one edge's
indicator exceeds half the gate, or ``max_update_interval_us`` has passed, the pose is re-solved
(``pose.refine_pose``), the edges are re-projected and the clusters re-binned, dropping events
now beyond the gate or too old.

Unlike the paper's static edges, these move between updates at the image velocity fitted to the
latest poses: an event is carried back along its edge's motion to the time the edges hold
before it is gated and binned, and at an update the clusters are carried forward to the
update's time. Static edges leave the pose behind the events, and under fast motion off the
ring.

A pose update must follow the marker, not the sensor: a still marker's ring fires nothing, and
a noisy sensor's leak and shot noise alone then fill the clusters, whose fits would walk the pose
away. An update needs an outer edge that fired since the last one, its events piled up at some
distance from it rather than spread evenly as noise spreads (``_edges_firing``).

Unlike the authors' tracker, this one also says when it is wrong: events in a band one ring wide
around the edges should lie on the edges; when most of them do not, the pose has slipped (see
``EdgeTracker.fit_ratio``). And a pose from detection is first pulled onto the ring's edges with
shrinking gates (``EdgeTracker.capture``), since a detection under motion is a few pixels off.
"""

from __future__ import annotations

import statistics
from collections import deque
from dataclasses import dataclass

import numba
import numpy as np

from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.pose import project_ideal, refine_pose

_MIN_EDGES = 4
"""Edges with enough fresh events for a pose solve: four lines fix a plane's pose."""
_CAPTURE_GATES = (2.0, 1.0, 0.0)
"""Gates of the capture passes in ring widths (0: the tracking gates). Each event counts for its
nearest edge only, so the ring's two sides stay apart, and never from deeper than ``_LOCATOR_GAP``
inside the inner edges, where the blinking inner locator begins one ring further in."""
_LOCATOR_GAP = 0.6
_DARK_MEMORY = 100
"""Pose solves over which the events' dark-side offset is pooled (each solve's weight decays by
1/100 at the next): the offset follows the optics and the screen's contrast, which hold for far
longer than a solve, while a single solve's estimate swings by half a pixel when few edges
fire."""
_CAPTURE_MIN_EVENTS = 50
_BLOCK = 64
"""Events whose distances to the edges ``_assign`` computes at a time."""
_SPREAD_BINS = 4
"""Bins of distance to an edge, out to two gates, that tell a firing edge from noise
(``_edges_firing``): half a gate wide, so that a lagging edge's events pile up in one."""
REVERSED_AGREEMENT = -1 / 3
"""An edge whose events agree with the polarity the motion gives it this badly (mean of +1 for
each with it, -1 against; here twice as many against) is fired by an edge of the other sign."""
_UNJUDGED = np.zeros(8, np.int64)
"""``_assign``'s expected polarities when the events come without theirs: none judged."""
_BIT_INDEX = np.zeros(37, np.int64)
_BIT_INDEX[[(1 << e) % 37 for e in range(36)]] = range(36)
"""Index of the single set bit of ``1 << e`` at ``(1 << e) % 37`` (the remainders of the
powers of two below 2**36 differ): an edge mask's lowest edge without a loop over the edges."""


@numba.njit(cache=True, nogil=True, inline="always")
def _inv_len2(dx, dy):
    """1 / the squared length of a segment (dx, dy), 0 for a point: ``_along``'s divisor,
    computed once per segment rather than once per event."""
    L2 = dx * dx + dy * dy
    return 1.0 / L2 if L2 > 0 else 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def _along(px, py, ax, ay, dx, dy, inv_len2):
    """Position (0..1) of point p's nearest point on the segment a -> a + (dx, dy)."""
    return min(max(((px - ax) * dx + (py - ay) * dy) * inv_len2, 0.0), 1.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _to_segment(px, py, ax, ay, dx, dy, inv_len2):
    """(distance, position along the segment in 0..1) of point p to segment a -> a + (dx, dy)."""
    w = _along(px, py, ax, ay, dx, dy, inv_len2)
    ex, ey = ax + w * dx - px, ay + w * dy - py
    return np.sqrt(ex * ex + ey * ey), w


@numba.njit(cache=True, nogil=True, inline="always")
def _line_far2(limit, dx, dy):
    """The squared cross product (``_off_line``) beyond which a point lies farther than ``limit``
    from the line of a segment (dx, dy), so from the segment too: cheaper than the exact
    distance, a division and a square root. The margin covers rounding."""
    return (limit * (1 + 1e-6)) ** 2 * (dx * dx + dy * dy)


@numba.njit(cache=True, nogil=True, inline="always")
def _off_line(px, py, ax, ay, dx, dy, far2):
    """Whether point p lies beyond ``far2`` (``_line_far2``) of the line through a, (dx, dy)."""
    cross = dx * (py - ay) - dy * (px - ax)
    return cross * cross > far2


@numba.njit(cache=True, nogil=True)
def _nearest_edge(xu, yu, a, b, reach=np.inf):
    """Distance to, and index of, the nearest projected edge of every point; a point farther
    than ``reach`` from every edge gets an infinite distance (and edge 0).

    Most points of a detection window lie in the data area, far from the ring: ``_off_line``
    rules those out before the exact distance."""
    n, m = xu.shape[0], a.shape[0]
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    far2 = _line_far2(reach, dx, dy)
    inv = np.array([_inv_len2(dx[e], dy[e]) for e in range(m)])
    dist, edge = np.full(n, np.inf), np.zeros(n, np.int64)
    for i in range(n):
        px, py = xu[i], yu[i]
        for e in range(m):
            if _off_line(px, py, a[e, 0], a[e, 1], dx[e], dy[e], far2[e]):
                continue
            d, _ = _to_segment(px, py, a[e, 0], a[e, 1], dx[e], dy[e], inv[e])
            if d < dist[i] and d <= reach:
                dist[i], edge[i] = d, e
    return dist, edge


def edge_polarities(a: np.ndarray, b: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """(8,) polarity (+1 ON, -1 OFF, 0 unknown) of the events that image ``flow`` (one (2,)
    for all, or (8, 2): each edge's own) fires on the ring's projected edges ``a[i] -> b[i]``
    (the outer ones, then the inner ones).

    An edge moving towards its dark side brightens its pixels. The white ring is the bright side
    of its outer edges and the dark gap inside it the dark side of its inner ones. Edges moving
    along themselves (under a quarter of the flow across them) are unknown."""
    flow = np.atleast_2d(np.asarray(flow, np.float64))
    return _polarities(np.asarray(a, np.float64), np.asarray(b, np.float64), flow)[0]


@numba.njit(cache=True, nogil=True)
def _polarities(a, b, flow):
    """``edge_polarities``, and each edge's speed across itself (|flow . normal|), with ``flow``
    (1, 2) or (8, 2). Compiled: the tracker asks at every pose update, where the dozens of
    small array operations it would take cost as much as the update's own fit."""
    n = a.shape[0]
    cx, cy = 0.0, 0.0
    for i in range(n):
        cx += a[i, 0] / n
        cy += a[i, 1] / n
    polarity, speed = np.zeros(n), np.zeros(n)
    for i in range(n):
        nx, ny = b[i, 1] - a[i, 1], a[i, 0] - b[i, 0]
        length = np.hypot(nx, ny)
        nx, ny = nx / length, ny / length
        if nx * (0.5 * (a[i, 0] + b[i, 0]) - cx) + ny * (0.5 * (a[i, 1] + b[i, 1]) - cy) < 0:
            nx, ny = -nx, -ny  # outwards
        f = flow[i if flow.shape[0] > 1 else 0]
        across = nx * f[0] + ny * f[1]
        speed[i] = abs(across)
        if speed[i] >= 0.25 * np.hypot(f[0], f[1]):
            polarity[i] = np.sign(across) * (1.0 if i < n // 2 else -1.0)
    return polarity, speed


@numba.njit(cache=True, nogil=True)
def _edge_layout(a, b, ring_m, world_len, gate_px, alpha):
    """(band, gate, bins) of each projected edge ``a[i] -> b[i]`` (the outer ones, then the
    inner ones) of world length ``world_len[i]``: the white ring's width ``ring_m`` in the image
    along it, theta_d (``gate_px``) narrowed where the ring is thin so that the blinking inner
    locator (one ring width inside the inner edges) never feeds a cluster, and ``alpha`` bins
    per pixel of its length (at least 3). Compiled, as the rest of a pose update: it runs ~1000
    times a second."""
    m = a.shape[0]
    band, gate, cap = np.empty(m), np.empty(m), np.empty(m, np.int64)
    for e in range(m):
        dx, dy = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
        length = np.sqrt(dx * dx + dy * dy)
        band[e] = length * ring_m / world_len[e]
        share = 0.45 if e < m // 2 else 0.3  # inner edges: near the locator
        gate[e] = min(gate_px, share * band[e])
        cap[e] = int(max(3.0, alpha * length))
    return band, gate, cap


@numba.njit(cache=True, nogil=True)
def _empty_slots(cap):
    """Empty clusters of ``cap[i]`` bins per edge: (x, y, time (-1: empty), distance) per bin,
    and per edge the distance sum and the count of filled bins."""
    m, width = cap.shape[0], cap.max()
    return (
        np.zeros((m, width)),
        np.zeros((m, width)),
        np.full((m, width), -1, np.int64),
        np.zeros((m, width)),
        np.zeros(m),
        np.zeros(m, np.int64),
    )


@numba.njit(cache=True, nogil=True)
def _capture_points(xu, yu, a, b, gate, deep_px, centre):
    """(whether it counts, nearest edge) of every point for a capture pass: it counts within
    its nearest edge's ``gate``, except more than ``deep_px`` on the centre side of an outer edge
    (4..7), which is nearer the ring's inner edge or the blinking locator than it looks."""
    dist, edge = _nearest_edge(xu, yu, a, b, gate.max())
    near = np.empty(xu.shape[0], np.bool_)
    for i in range(xu.shape[0]):
        e = edge[i]
        near[i] = dist[i] <= gate[e]
        if near[i] and e >= 4 and dist[i] > deep_px[e]:
            dx, dy = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
            side = dx * (yu[i] - a[e, 1]) - dy * (xu[i] - a[e, 0])
            ref = dx * (centre[1] - a[e, 1]) - dy * (centre[0] - a[e, 0])
            near[i] = not side * ref > 0
    return near, edge


@numba.njit(cache=True, nogil=True, inline="always")
def _late(sum_d, n_valid, cap, gate, min_fill):
    """An edge's latency indicator fired: its cluster is filled enough and lies, on average,
    more than half the gate off the edge."""
    return n_valid >= max(3, min_fill * cap) and sum_d > 0.5 * gate * n_valid


@numba.njit(cache=True, nogil=True)
def _assign(
    xu,
    yu,
    t,
    pol,
    start,
    a,
    b,
    va,
    vb,
    ref_us,
    gate,
    band,
    cap,
    sx,
    sy,
    st,
    sd,
    sum_d,
    n_valid,
    fit,
    spread,
    expected,
    tally,
    due_us,
    force_us,
    min_fill,
    min_new,
    carry_us,
):
    """Add events ``start..`` to the clusters and count, in ``fit``, events in the band around
    the edges, those of them on an edge, and events on an edge since the last update; and per
    edge, in ``spread``, the events by their distance to it in ``_SPREAD_BINS`` bins out to two
    gates (``_edges_firing``); and per edge of ``expected`` polarity (+1, -1; 0: none), in
    ``tally``, the events on it of that polarity and of the other (``reversed_edges``). The edges
    a -> b hold at ``ref_us`` and move at the ends' velocities ``va``, ``vb`` (px/us): each event
    is carried back to ``ref_us`` (``carry_us`` at most) along an edge's motion before it is
    measured and binned. Stop after the first event that makes more than one indicator exceed
    half its gate (at or after ``due_us``), or at ``force_us`` once ``min_new`` new events
    joined. Returns (index to resume from, whether it stopped)."""
    # In blocks of events: first the distance of each event to each edge, edge by edge over
    # the block (no branch, contiguous: the compiler vectorises it), then the binning in event
    # order. Event by event, the eight distances' arithmetic and branches dominate the cost,
    # and ruling edges out first saves little.
    m = a.shape[0]
    ax, ay = a[:, 0].copy(), a[:, 1].copy()
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    vx, vy = va[:, 0].copy(), va[:, 1].copy()
    dvx, dvy = vb[:, 0] - va[:, 0], vb[:, 1] - va[:, 1]  # the velocity varies linearly along it
    inv, per_px = np.empty(m), np.empty(m)
    late = np.zeros(m, np.bool_)
    for e in range(m):
        inv[e] = _inv_len2(dx[e], dy[e])
        per_px[e] = _SPREAD_BINS / (2.0 * gate[e])  # ``spread``'s bins per pixel of distance
        late[e] = _late(sum_d[e], n_valid[e], cap[e], gate[e], min_fill)
    n_late = late.sum()  # kept up to date as events join, instead of recounted per event
    x, y, dt = np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK)
    qx, qy = np.empty((m, _BLOCK)), np.empty((m, _BLOCK))
    along, dist = np.empty((m, _BLOCK)), np.empty((m, _BLOCK))
    on_edges, near = np.empty(_BLOCK, np.int64), np.empty(_BLOCK, np.bool_)
    in_strip = np.empty(_BLOCK, np.int64)
    for b0 in range(start, t.shape[0], _BLOCK):
        nb = min(_BLOCK, t.shape[0] - b0)
        for j in range(nb):
            x[j], y[j] = xu[b0 + j], yu[b0 + j]
            dt[j] = min(max(t[b0 + j] - ref_us, -carry_us), carry_us)
        for e in range(m):  # the events as the edge's motion places them at ``ref_us``
            for j in range(nb):
                w = _along(x[j], y[j], ax[e], ay[e], dx[e], dy[e], inv[e])
                px = x[j] - (vx[e] + w * dvx[e]) * dt[j]
                py = y[j] - (vy[e] + w * dvy[e]) * dt[j]
                dist[e, j], along[e, j] = _to_segment(px, py, ax[e], ay[e], dx[e], dy[e], inv[e])
                qx[e, j], qy[e, j] = px, py
        # Which edges each event is on (bit e), and whether it is in the band: also edge by
        # edge, since tested per event the eight gates' branches mispredict.
        on_edges[:nb], near[:nb], in_strip[:nb] = 0, False, 0
        for e in range(m):
            for j in range(nb):
                on_edges[j] |= np.int64(dist[e, j] <= gate[e]) << e
                near[j] |= dist[e, j] <= band[e]
                in_strip[j] |= np.int64(dist[e, j] <= 2.0 * gate[e]) << e
        for j in range(nb):
            i = b0 + j
            edges = on_edges[j]
            while edges:
                lowest = edges & -edges
                edges ^= lowest
                e = _BIT_INDEX[lowest % 37]
                d = dist[e, j]
                # Into bin s, replacing its older event in the count and distance sum. Written
                # out here: a helper taking the six arrays makes numba keep a dozen atomic
                # reference counts per call.
                s = min(int(along[e, j] * cap[e]), cap[e] - 1)
                if st[e, s] >= 0:
                    sum_d[e] -= sd[e, s]
                else:
                    n_valid[e] += 1
                sx[e, s], sy[e, s], st[e, s], sd[e, s] = qx[e, j], qy[e, j], t[i], d
                sum_d[e] += d
                if expected[e] != 0:
                    tally[e, 1 if pol[i] * expected[e] < 0 else 0] += 1
                now_late = _late(sum_d[e], n_valid[e], cap[e], gate[e], min_fill)
                n_late += now_late - late[e]
                late[e] = now_late
            strip = in_strip[j]
            while strip:
                lowest = strip & -strip
                strip ^= lowest
                e = _BIT_INDEX[lowest % 37]
                spread[e, min(int(dist[e, j] * per_px[e]), _SPREAD_BINS - 1)] += 1
            on = on_edges[j] != 0
            if near[j]:
                fit[0] += 1
                fit[1] += on
            fit[2] += on
            if t[i] >= force_us and fit[2] >= min_new:
                return i + 1, True
            if t[i] >= due_us and n_late > 1:
                return i + 1, True
    return t.shape[0], False


@numba.njit(cache=True, nogil=True, inline="always")
def _resum(e, st, sd, sum_d, n_valid):
    """Recount edge ``e``'s cluster in slot order: re-binnings of the same slots then give the
    same indicators bit for bit, whatever order their events arrived in."""
    total, count = 0.0, 0
    for s in range(st.shape[1]):
        if st[e, s] >= 0:
            total += sd[e, s]
            count += 1
    sum_d[e], n_valid[e] = total, count


@numba.njit(cache=True, nogil=True)
def _reassign(old_x, old_y, old_t, since_us, a, b, gate, cap, sx, sy, st, sd, sum_d, n_valid):
    """Move the old clusters' events not older than ``since_us`` into the new (empty) clusters,
    each only onto the edge it was on and the newest winning its bin: ``_assign``'s binning for
    one edge, without its indicators and fit counts (the re-binned events were counted in the
    fit already). Runs at every pose update."""
    for e in range(old_t.shape[0]):
        dx, dy = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
        inv = _inv_len2(dx, dy)
        for i in range(old_t.shape[1]):
            t = old_t[e, i]
            if t < since_us:  # stale, or an empty slot (-1)
                continue
            px, py = old_x[e, i], old_y[e, i]
            d, w = _to_segment(px, py, a[e, 0], a[e, 1], dx, dy, inv)
            s = min(int(w * cap[e]), cap[e] - 1)
            if d <= gate[e] and st[e, s] <= t:
                sx[e, s], sy[e, s], st[e, s], sd[e, s] = px, py, t, d
        _resum(e, st, sd, sum_d, n_valid)


@numba.njit(cache=True, nogil=True)
def _age_out(since_us, sx, sy, st, sd, sum_d, n_valid):
    """Empty the bins older than ``since_us`` in place: ``_reassign`` onto the same edges, where
    every kept event lands in its own bin again."""
    for e in range(st.shape[0]):
        for i in range(st.shape[1]):
            if st[e, i] < since_us:
                sx[e, i], sy[e, i], st[e, i], sd[e, i] = 0.0, 0.0, -1, 0.0
        _resum(e, st, sd, sum_d, n_valid)


@numba.njit(cache=True, nogil=True)
def _supported_edges(st, since_us, cap, min_fill):
    """Which edges hold at least ``max(3, min_fill * cap)`` events not older than
    ``since_us``."""
    supported = np.zeros(st.shape[0], np.bool_)
    for e in range(st.shape[0]):
        fresh = 0
        for s in range(st.shape[1]):
            fresh += st[e, s] >= since_us
        supported[e] = fresh >= max(3, min_fill * cap[e])
    return supported


@numba.njit(cache=True, nogil=True)
def _edges_firing(spread, a, b, gate, min_chi2):
    """Which edges fire: their events since the last update (``spread``: counts by distance in
    ``_SPREAD_BINS`` bins out to two gates) pile up at some distance, rather than spread as
    evenly over the bins' areas as the sensor's leak and shot noise do (Pearson's chi-square
    against that even spread above ``min_chi2``).

    Out to two gates the marker is static on both sides of the ring's edges (the white ring,
    the black rings beside it; the inner gates keep away from the blinking locator), so while
    it stands still only noise fires there: however fully the noise fills the clusters, it
    never piles up along an edge. A moving edge does, at its offset from the projected one
    when the pose lags, and whatever the noise's density. Each bin straddles the edge, as
    wide on its bright side as on its dark one, so a noise density differing between the white
    ring and the dark rings (shot noise fires more in the dark) spreads evenly all the same."""
    m, k = spread.shape
    firing = np.zeros(m, np.bool_)
    for e in range(m):
        n = spread[e].sum()
        if n == 0:
            continue
        dx, dy = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
        length, w = np.sqrt(dx * dx + dy * dy), 2.0 * gate[e] / k
        total = 2.0 * length * k * w + np.pi * (k * w) ** 2  # the area out to two gates
        chi2 = 0.0
        for i in range(k):
            area = 2.0 * length * w + np.pi * w * w * (2 * i + 1)  # distances i*w .. (i+1)*w
            expected = n * area / total
            chi2 += (spread[e, i] - expected) ** 2 / expected
        firing[e] = chi2 > min_chi2
    return firing


@numba.njit(cache=True, nogil=True)
def _fresh_points(sx, sy, st, since_us):
    """(points (n, 2), their edges) of the slots not older than ``since_us``, edge by edge."""
    n = 0
    for e in range(st.shape[0]):
        for s in range(st.shape[1]):
            n += st[e, s] >= since_us
    pts, edge = np.empty((n, 2)), np.empty(n, np.int64)
    k = 0
    for e in range(st.shape[0]):
        for s in range(st.shape[1]):
            if st[e, s] >= since_us:
                pts[k, 0], pts[k, 1], edge[k] = sx[e, s], sy[e, s], e
                k += 1
    return pts, edge


@numba.njit(cache=True, nogil=True)
def _carry(sx, sy, st, cap, va, vb, ref_us, now_us, carry_us):
    """Carry the slots' events, placed as of ``ref_us``, forward to ``now_us`` along the edges'
    motion (an event ``carry_us`` from its own time at most), in place; a slot's place along
    its edge is its bin's centre."""
    for e in range(st.shape[0]):
        for s in range(cap[e]):
            if st[e, s] < 0:
                continue
            dt = min(max(now_us - st[e, s], -carry_us), carry_us)
            dt -= min(max(ref_us - st[e, s], -carry_us), carry_us)
            w = (s + 0.5) / cap[e]
            sx[e, s] += (va[e, 0] + w * (vb[e, 0] - va[e, 0])) * dt
            sy[e, s] += (va[e, 1] + w * (vb[e, 1] - va[e, 1])) * dt


@numba.njit(cache=True, nogil=True)
def _median_speed(va, vb):
    """Median over the edges of the speed of their middles, moving at ``(va + vb) / 2``
    (compiled: the tracker asks after every push, and numpy's per-call overhead would
    dominate)."""
    speed = np.empty(va.shape[0])
    for e in range(va.shape[0]):
        speed[e] = 0.5 * np.hypot(va[e, 0] + vb[e, 0], va[e, 1] + vb[e, 1])
    return np.median(speed)


@numba.njit(cache=True, nogil=True)
def _recent_velocity(times, ends, n, now_us, a, b, span_us):
    """Append the projected ends ``a``, ``b`` of the edges at ``now_us`` to the first ``n`` of
    the recent poses' ``times`` (k,) and ends (k, 16, 2), dropping the oldest beyond
    ``span_us`` while more than three remain; return their new count and, from three
    on, the least-squares velocity (px/us) of each end over them (a line per coordinate)."""
    m = a.shape[0]
    times[n] = now_us
    ends[n, :m], ends[n, m:] = a, b
    n += 1
    drop = 0
    while n - drop > 3 and now_us - times[drop] > span_us:
        drop += 1
    if drop:
        n -= drop
        times[:n] = times[drop : drop + n].copy()
        ends[:n] = ends[drop : drop + n].copy()
    v = np.zeros((2 * m, 2))
    if n < 3:
        return n, v
    tc = times[:n] - times[:n].mean()
    for i in range(n):
        v += tc[i] * ends[i]
    return n, v / np.dot(tc, tc)


@dataclass
class TrackUpdate:
    t_us: int
    T_cam_world: np.ndarray
    cost: float
    support: int


class EdgeTracker:
    """Clusters + pose for one tracking session (created at each (re-)detection)."""

    def __init__(
        self,
        config: ReceiverConfig,
        T_cam_world: np.ndarray,
        now_us: int = 0,
        flow_px_per_ms: np.ndarray | None = None,
    ) -> None:
        """Track from ``T_cam_world`` at ``now_us``; ``flow_px_per_ms`` is the image flow known
        at that time (from detection under motion), the edges' velocity until poses give it."""
        self.config = config
        geo = config.geometry
        self.edges_world = geo.tracked_edges(config.marker_size_m)
        self._ring_m = geo.ring * geo.cell_size_m(config.marker_size_m)
        self._world_len = np.linalg.norm(self.edges_world[:, 1] - self.edges_world[:, 0], axis=1)
        self.K = config.camera.K
        self.T_cam_world = T_cam_world
        self.dark_px = 0.0
        """How far the edges' events lie to their dark side, fitted with each pose
        (``pose.refine_pose``) and pooled over the latest ``_DARK_MEMORY`` solves."""
        self.dark_weight = 0.0
        """The points ``dark_px`` was fitted to, the older solves' decayed."""
        self.last_update_us = now_us
        self._last_rebin_us = now_us
        self._slots = None
        flow = np.zeros(2) if flow_px_per_ms is None else np.asarray(flow_px_per_ms) / 1e3
        self._va = self._vb = np.tile(flow, (8, 1))
        """Image velocity (px/us) of the edges' ends, fitted to the latest poses."""
        self._recent_t, self._recent_ends = np.empty(16), np.empty((16, 16, 2))
        """Times and the edges' projected ends of the latest ``_n_recent`` poses."""
        self._n_recent = 0
        self._fit = np.zeros(3, np.int64)
        self._spread = np.zeros((8, _SPREAD_BINS), np.int64)
        """Per edge, the events since the last update by their distance to it
        (``_edges_firing``)."""
        self.fit_history: deque[float] = deque(maxlen=config.tracker.fit_judgements)
        """The latest ``fit_judgements`` fit ratios, oldest first."""
        self.silent_history: deque[int] = deque(maxlen=config.tracker.silent_updates)
        """``silent_edges`` at the latest pose updates, oldest first."""
        self._tally = np.zeros((8, 2), np.int64)
        """Per edge, its events of the expected polarity and of the other, since
        ``_tally_since_us`` (``reversed_edges``)."""
        self._tally_since_us = now_us
        self._reversed_runs = np.zeros(8, np.int64)
        """Per edge, the latest judged windows in a row in which it fired reversed."""
        self.agreement = np.full(8, np.nan)
        """Per edge, its events' agreement with the motion's polarity (-1..1) in the latest
        closed window, NaN where unjudged (``_judge_polarities``)."""
        self.best_agreement = np.full(8, np.nan)
        """Per edge, the best of its ``agreement`` since the tracker began."""
        self._rebin(T_cam_world, now_us)
        self._expected = self._swept()
        """Per edge, the polarity its events have while the image sweeps it (``_swept``)."""

    @property
    def edges_px(self) -> tuple[np.ndarray, np.ndarray]:
        """The tracked edges' ends a -> b (each (8, 2), ideal pixels) at the current pose."""
        return self._a, self._b

    @property
    def fit_ratio(self) -> float | None:
        """Share of the latest band events that lie on an edge, judged while the image moves
        (``TrackerParams.min_fit_speed_px_per_ms``); None until enough were seen."""
        return self.fit_history[-1] if self.fit_history else None

    @property
    def image_speed_px_per_ms(self) -> float:
        """Median speed of the edges' middles in the image."""
        return _median_speed(self._va, self._vb) * 1e3

    @property
    def contradicted(self) -> bool:
        """Whether each of the last ``silent_updates`` pose updates found a silent swept outer
        edge (``silent_edges``)."""
        history = self.silent_history
        return len(history) == history.maxlen and all(history)

    def off_edges(self) -> str | None:
        """Why the tracked pose has left the ring, if it has: an outer edge silent while the
        motion sweeps it (``contradicted``), or the last ``fit_judgements`` fit ratios' median
        below ``min_fit_ratio``. One low judgement is how a right pose looks for a moment under
        slow motion (few edge events, the blinking locator beside the ring)."""
        if self.contradicted:
            return "an outer edge of the ring shows no events while the marker sweeps it"
        if self.reversed_edges():
            return (
                "a ring edge fires against the motion at the tracked pose, as one a ring width "
                "off does"
            )
        history = self.fit_history
        if len(history) < history.maxlen:
            return None
        ratio = statistics.median(history)  # after every push: cheaper than numpy's
        if ratio < self.config.tracker.min_fit_ratio:
            return f"only {ratio:.0%} of the events near the ring lie on its edges"
        return None

    def reversed_edges(self) -> bool:
        """Whether an edge fired mostly against the motion in each of the last
        ``reversed_windows`` judged windows (``_judge_polarities``). A right pose's swept edges
        fire as the motion makes them (the white ring's outer ones brighten moving outwards),
        while a side fitted a ring width off lies on an edge of the other sign: the white ring's
        inner edge or the black ring's outer one. Such a pose reads the locator's 'L' and
        passes every other check, its error in the side's position the camera's in depth and
        tilt."""
        return bool(self._reversed_runs.max() >= self.config.tracker.reversed_windows)

    def _judge_polarities(self, now_us: int) -> None:
        """Close the polarity tally's window once it spans ``polarity_window_us``: an edge with
        ``min_polarity_events`` swept events fired reversed when they agreed with the expected
        polarity at ``REVERSED_AGREEMENT`` or worse."""
        q = self.config.tracker
        if now_us - self._tally_since_us < q.polarity_window_us:
            return
        with_motion, against = self._tally[:, 0], self._tally[:, 1]
        n = with_motion + against
        judged = n >= q.min_polarity_events
        self.agreement = np.where(judged, (with_motion - against) / np.maximum(n, 1), np.nan)
        self.best_agreement = np.fmax(self.best_agreement, self.agreement)
        reversed_ = judged & (self.agreement <= REVERSED_AGREEMENT)
        self._reversed_runs = np.where(
            reversed_, self._reversed_runs + 1, np.where(judged, 0, self._reversed_runs)
        )
        self._tally[:] = 0
        self._tally_since_us = now_us

    def _swept(self) -> np.ndarray:
        """(8,) polarity of each outer edge's events (``edge_polarities``) while the image
        crosses it at ``polarity_sweep_px_per_ms`` or faster and at half the fastest edge's
        speed across itself, 0 otherwise. Slower, the edge's own events are too few for the
        sensor's noise (the leak fires ON alone) to leave their polarity, or the velocity's
        error (fitted to poses that jitter between tilt and shift) can turn its sign. The inner
        edges are not judged: the blinking locator, a ring width inside, fires both ways within
        their gates when the ring is thin."""
        velocity = 0.5 * (self._va + self._vb) * 1e3  # px/ms, each edge's middle
        polarity, across = _polarities(self._a, self._b, velocity)
        swept = across >= max(self.config.tracker.polarity_sweep_px_per_ms, 0.5 * across.max())
        swept[4:] = False
        return np.where(swept, polarity, 0).astype(np.int64)

    def silent_edges(self, supported: np.ndarray) -> int:
        """Outer edges that hold no fresh events (``supported``: per edge) although the image
        moves them across themselves faster than ``silent_sweep_px_per_ms`` inside the view and
        the inner edge beside them holds fresh ones. A correct pose has none: the white ring's
        two edges sweep over the same motion. A pose that fits the ring's two near sides and,
        on the other two, takes the screen's border for the ring's inner edge (the same
        contrast: bright outside, dark inside) has two: its outer edges lie on the wall around
        the screen, where nothing fires, while most of its band's events lie on its edges."""
        silent = ~supported[:4] & supported[4:]
        if not silent.any():  # a tracked pose's usual case: skip the geometry (every update)
            return 0
        speed = _polarities(self._a, self._b, 0.5 * (self._va + self._vb))[1][:4]
        ends, cam = np.stack([self._a[:4], self._b[:4]], 1), self.config.camera
        inside = np.all((ends >= 0) & (ends < (cam.width, cam.height)), axis=(1, 2))
        sweep = self.config.tracker.silent_sweep_px_per_ms / 1e3  # px/us, as the velocity
        return int(np.count_nonzero(silent & (speed > sweep) & inside))

    # --- geometry of the current pose ----------------------------------------------------------
    def _project_edges(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        px = project_ideal(T, self.K, self.edges_world)  # (8, 2, 2)
        return np.ascontiguousarray(px[:, 0]), np.ascontiguousarray(px[:, 1])

    def _layout(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(band, gate, bins) of the projected edges ``a[i] -> b[i]`` (``_edge_layout``)."""
        q = self.config.tracker
        return _edge_layout(a, b, self._ring_m, self._world_len, q.gate_px, q.alpha)

    def _rebin(self, T: np.ndarray, now_us: int) -> None:
        a, b = self._project_edges(T)
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            raise ValueError("marker behind the camera")
        old = self._slots
        self._a, self._b = a, b
        self._band, self._gate, self._cap = self._layout(a, b)
        self._slots = _empty_slots(self._cap)
        self._ref_us = self._last_rebin_us = now_us  # the edges hold at ``now_us``
        if old is None:
            return
        since = max(0, now_us - self.config.tracker.max_age_us)
        _reassign(old[0], old[1], old[2], since, a, b, self._gate, self._cap, *self._slots)

    def _age_out(self, now_us: int) -> None:
        """``_rebin`` at the current pose (whose edges the clusters already follow): only the
        stale slots leave. A still camera's noise asks for this every millisecond."""
        since = max(0, now_us - self.config.tracker.max_age_us)
        _age_out(since, *self._slots)
        self._last_rebin_us = now_us

    # --- start ---------------------------------------------------------------------------------
    def capture(
        self,
        xu: np.ndarray,
        yu: np.ndarray,
        now_us: int,
        motion: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> bool:
        """Pull the pose onto recent events of the ring's edges (from within about one ring width
        of them), in passes of shrinking gates. Returns False, keeping the pose, when the edges
        have too few events (a still camera: then the detection itself is accurate).

        ``motion`` = (the events' polarities, the image flow in px/ms): an event then counts
        for an edge only with the polarity the flow gives that edge (``edge_polarities``), so
        that the edges of the black ring around the white one, an edge of the other sign a ring
        width further out, do not pull the pose."""
        q = self.config.tracker
        T = self.T_cam_world
        for scale in _CAPTURE_GATES:
            a, b = self._project_edges(T)
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
                return False
            ring_px, gate, _ = self._layout(a, b)
            gate = scale * ring_px if scale else gate
            near, edge = _capture_points(xu, yu, a, b, gate, _LOCATOR_GAP * ring_px, a.mean(axis=0))
            if motion is not None:
                expected = edge_polarities(a, b, motion[1])[edge]
                near &= (expected == 0) | (motion[0] * expected > 0)
            if np.count_nonzero(near) < _CAPTURE_MIN_EVENTS or len(np.unique(edge[near])) < 4:
                return False
            pts = np.stack([xu[near], yu[near]], 1)
            T, _, _, _ = refine_pose(
                T,
                self.K,
                pts,
                edge[near],
                self.edges_world,
                q.huber_px,
                q.max_iterations,
                self.dark_px,
                np.inf,
            )
        if not np.all(np.isfinite(self._project_edges(T))):
            return False  # the last pass put the marker behind the camera
        self.restart(T, now_us)
        return True

    def restart(self, T_cam_world: np.ndarray, now_us: int) -> None:
        """Track on from ``T_cam_world`` at ``now_us``: the clusters and the poses the edges'
        velocity was fitted to belonged to the old pose."""
        self.T_cam_world = T_cam_world
        self._slots = None
        self._n_recent = 0
        self._rebin(T_cam_world, now_us)
        self._expected = self._swept()

    # --- streaming -----------------------------------------------------------------------------
    def push(
        self, xu: np.ndarray, yu: np.ndarray, t: np.ndarray, p: np.ndarray | None = None
    ) -> list[TrackUpdate]:
        """Feed events (ideal pixels, time-sorted, and polarities ``p``: without them, the
        edges' polarities go unjudged); returns the pose updates they triggered."""
        updates = []
        expected = self._expected if p is not None else _UNJUDGED
        p = np.zeros(len(t), np.int8) if p is None else p
        start = 0
        q = self.config.tracker
        while start < len(t):
            sx, sy, st, sd, sum_d, n_valid = self._slots
            stop, due = _assign(
                xu,
                yu,
                t,
                p,
                start,
                self._a,
                self._b,
                self._va,
                self._vb,
                self._ref_us,
                self._gate,
                self._band,
                self._cap,
                sx,
                sy,
                st,
                sd,
                sum_d,
                n_valid,
                self._fit,
                self._spread,
                expected,
                self._tally,
                self.last_update_us + q.min_update_interval_us,
                self.last_update_us + q.max_update_interval_us,
                q.min_fill,
                q.min_new_events,
                q.carry_us,
            )
            now = int(t[stop - 1])
            if due:
                update = self._update(now)
                if update is not None:
                    updates.append(update)
            elif now - self._last_rebin_us >= q.max_age_us // 2:
                self._age_out(now)  # stale slots leave the indicators
            start = stop
        if self._fit[0] >= q.fit_min_events:
            if self.image_speed_px_per_ms >= q.min_fit_speed_px_per_ms:
                self.fit_history.append(float(self._fit[1] / self._fit[0]))
            self._fit[:2] = 0
        return updates

    def _update(self, now_us: int) -> TrackUpdate | None:
        """Re-solve the pose, unless too few edges hold fresh events, or no outer edge has fired
        since the last update (``_edges_firing``): noise alone must not move a camera that
        stands still, however fully it fills the clusters. The outer edges alone judge: the
        blinking locator lies a ring width inside the inner ones, two gates off at the least,
        which a blurred burst reaches. Under motion at least two of them fire, those the image
        crosses (motion along an edge fires nothing there), while the others' clusters still
        hold what they fired last."""
        sx, sy, st = self._slots[:3]
        q = self.config.tracker
        self.last_update_us = now_us
        self._fit[2] = 0
        since = max(0, now_us - q.max_age_us)
        supported = _supported_edges(st, since, self._cap, q.min_fill)
        firing = _edges_firing(self._spread, self._a, self._b, self._gate, q.min_firing_chi2)
        self._spread[:] = 0
        self.silent_history.append(self.silent_edges(supported))
        self._judge_polarities(now_us)
        if np.count_nonzero(supported) < _MIN_EDGES or not firing[:4].any():
            self._age_out(now_us)
            return None
        _carry(sx, sy, st, self._cap, self._va, self._vb, self._ref_us, now_us, q.carry_us)
        pts, edge = _fresh_points(sx, sy, st, since)
        prior = self.dark_weight * (1 - 1 / _DARK_MEMORY)
        T, cost, self.dark_px, weight = refine_pose(
            self.T_cam_world,
            self.K,
            pts,
            edge,
            self.edges_world,
            q.huber_px,
            q.max_iterations,
            self.dark_px,
            prior,
        )
        self.dark_weight = prior + weight
        self.T_cam_world = T
        self._rebin(T, now_us)
        self._fit_velocity(now_us)
        self._expected = self._swept()
        return TrackUpdate(now_us, T, cost, len(edge))

    def _fit_velocity(self, now_us: int) -> None:
        """Fit the edges' ends' image velocity to the poses of the last ``velocity_span_us``,
        or the last three (least squares, a line per coordinate); until three, keep the old."""
        if self._n_recent == len(self._recent_t):  # updates denser than ever: grow
            self._recent_t = np.concatenate([self._recent_t, np.empty_like(self._recent_t)])
            self._recent_ends = np.concatenate([self._recent_ends, self._recent_ends])
        self._n_recent, v = _recent_velocity(
            self._recent_t,
            self._recent_ends,
            self._n_recent,
            now_us,
            self._a,
            self._b,
            self.config.tracker.velocity_span_us,
        )
        if self._n_recent >= 3:
            self._va, self._vb = v[:8], v[8:]
