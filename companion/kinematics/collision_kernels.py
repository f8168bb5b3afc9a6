"""Compiled twin of :meth:`companion.kinematics.collision.KeepOut.clearances_reference`.

The numpy version spends its time in per-call overhead (about 150 small array operations per
configuration, ~0.3–1 ms): too much for a check on every 50 Hz control tick. This kernel does
the same arithmetic in scalar loops, compiled by numba (on first use, cached on disk like the
solver's kernels in :mod:`companion.ik.kernels`; ``python -m companion.ik`` compiles both ahead
of time, through :func:`warm_up`). ``tests/kinematics/test_collision.py`` holds
the two equal (``test_compiled_clearances_equal_the_reference``); the reference's docstrings say
what is computed and why it is exact or conservative.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from companion.kinematics.numba_cache import cache_usable


def _probe() -> int:
    return 0


#: numba caches this module's kernels on disk (see :mod:`companion.kinematics.numba_cache`).
CACHE = cache_usable(_probe, "keep-out kernels")

_TINY = 1e-18


@nb.njit(cache=CACHE)
def _segment_segment(p1, q1, p2, q2):  # pragma: no cover - compiled
    """Distance between segments p1q1 and p2q2 (Ericson §5.1.9), 3-vectors."""
    d1x, d1y, d1z = q1[0] - p1[0], q1[1] - p1[1], q1[2] - p1[2]
    d2x, d2y, d2z = q2[0] - p2[0], q2[1] - p2[1], q2[2] - p2[2]
    rx, ry, rz = p1[0] - p2[0], p1[1] - p2[1], p1[2] - p2[2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    s = 0.0
    t = 0.0
    if a <= _TINY and e <= _TINY:
        s = 0.0
        t = 0.0
    elif a <= _TINY:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= _TINY:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            denom = a * e - b * b
            if denom > _TINY * max(a * e, 1.0):
                s = min(max((b * f - c * e) / denom, 0.0), 1.0)
            else:
                s = 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    gx = rx + s * d1x - t * d2x
    gy = ry + s * d1y - t * d2y
    gz = rz + s * d1z - t * d2z
    return math.sqrt(gx * gx + gy * gy + gz * gz)


@nb.njit(cache=CACHE)
def _segment_box(p0, p1, half, ts):  # pragma: no cover - compiled
    """Distance from segment p0p1 to the box |x_k| <= half[k] (box frame); ``ts`` is a
    scratch array of 8."""
    n = 2
    ts[0] = 0.0
    ts[1] = 1.0
    for k in range(3):
        d = p1[k] - p0[k]
        if abs(d) > 1e-15:
            for bound in (half[k], -half[k]):
                t = (bound - p0[k]) / d
                ts[n] = min(max(t, 0.0), 1.0)
                n += 1
    for i in range(1, n):  # insertion sort of at most 8 values
        v = ts[i]
        j = i - 1
        while j >= 0 and ts[j] > v:
            ts[j + 1] = ts[j]
            j -= 1
        ts[j + 1] = v
    best = math.inf
    for i in range(n - 1):
        lo = ts[i]
        hi = ts[i + 1]
        mid = 0.5 * (lo + hi)
        ab = 0.0
        bb = 0.0
        for k in range(3):
            d = p1[k] - p0[k]
            x = p0[k] + mid * d
            if x > half[k]:
                ab += (p0[k] - half[k]) * d
                bb += d * d
            elif x < -half[k]:
                ab += (p0[k] + half[k]) * d
                bb += d * d
        t = lo
        if bb > 0.0:
            t = min(max(-ab / bb, lo), hi)
        sq = 0.0
        for k in range(3):
            d = p1[k] - p0[k]
            x = p0[k] + mid * d
            if x > half[k]:
                g = p0[k] - half[k] + t * d
                sq += g * g
            elif x < -half[k]:
                g = p0[k] + half[k] + t * d
                sq += g * g
        if sq < best:
            best = sq
    return math.sqrt(best)


@nb.njit(cache=CACHE)
def clearances(
    q,
    frames,
    directions,
    offsets,
    revolute,
    mount,
    cap_link,
    cap_ends,
    cap_radius,
    vcap_a,
    vcap_b,
    vcap_r,
    vbox_inv,
    vbox_half,
    cap_of,
    box_of,
    rounding,
    out,
):  # pragma: no cover - compiled
    """``out[s, c, v]``: the clearance lower bound of capsule ``c`` against volume ``v`` at
    configuration ``q[s]`` (cm); see ``KeepOut.clearances_reference``."""
    n_s, n = q.shape
    n_c = cap_link.shape[0]
    n_v = cap_of.shape[0]
    links = np.empty((n, 4, 4))
    t = np.empty((4, 4))
    tmp = np.empty((4, 4))
    p = np.empty(3)
    e = np.empty(3)
    pl = np.empty(3)
    el = np.empty(3)
    ts = np.empty(8)
    for s in range(n_s):
        # The link frames in the body frame: mount · F_0 · M_1 · … (as Arm.joint_frames).
        for i in range(4):
            for j in range(4):
                acc = 0.0
                for k in range(4):
                    acc += mount[i, k] * frames[0, k, j]
                t[i, j] = acc
        for joint in range(n):
            value = directions[joint] * q[s, joint] + offsets[joint]
            if revolute[joint]:
                c = math.cos(value)
                sn = math.sin(value)
                for i in range(4):
                    x = t[i, 0]
                    y = t[i, 1]
                    t[i, 0] = x * c + y * sn
                    t[i, 1] = y * c - x * sn
            else:
                for i in range(4):
                    t[i, 3] += t[i, 2] * value
            links[joint] = t
            for i in range(4):
                for j in range(4):
                    acc = 0.0
                    for k in range(4):
                        acc += t[i, k] * frames[joint + 1, k, j]
                    tmp[i, j] = acc
            t[:, :] = tmp
        for cap in range(n_c):
            g = links[cap_link[cap]]
            for i in range(3):
                p[i] = (
                    g[i, 0] * cap_ends[cap, 0, 0]
                    + g[i, 1] * cap_ends[cap, 0, 1]
                    + g[i, 2] * cap_ends[cap, 0, 2]
                    + g[i, 3]
                )
                e[i] = (
                    g[i, 0] * cap_ends[cap, 1, 0]
                    + g[i, 1] * cap_ends[cap, 1, 1]
                    + g[i, 2] * cap_ends[cap, 1, 2]
                    + g[i, 3]
                )
            for v in range(n_v):
                d = -math.inf
                k = cap_of[v]
                if k >= 0:
                    d = max(d, _segment_segment(p, e, vcap_a[k], vcap_b[k]) - vcap_r[k])
                for slot in range(2):
                    k = box_of[v, slot]
                    if k >= 0:
                        m = vbox_inv[k]
                        for i in range(3):
                            pl[i] = m[i, 0] * p[0] + m[i, 1] * p[1] + m[i, 2] * p[2] + m[i, 3]
                            el[i] = m[i, 0] * e[0] + m[i, 1] * e[1] + m[i, 2] * e[2] + m[i, 3]
                        d = max(d, _segment_box(pl, el, vbox_half[k], ts))
                out[s, cap, v] = d - cap_radius[cap] - rounding
    return out


_warmed_up = False


def warm_up() -> None:
    """Compile (or load from the cache) :func:`clearances` with the types the checks pass:
    about 10 s of CPU on a cold cache, some 20 ms warm. Later calls do nothing."""
    global _warmed_up
    if _warmed_up:
        return
    _warmed_up = True
    q = np.zeros((1, 1))
    box = np.eye(4).reshape(1, 4, 4)
    clearances(
        q,
        np.stack([np.eye(4), np.eye(4)]),
        np.ones(1),
        np.zeros(1),
        np.ones(1, dtype=np.bool_),
        np.eye(4),
        np.zeros(1, dtype=np.intp),
        np.zeros((1, 2, 3)),
        np.ones(1),
        np.zeros((1, 3)),
        np.zeros((1, 3)),
        np.ones(1),
        box,
        np.ones((1, 3)),
        np.zeros(1, dtype=np.intp),
        np.zeros((1, 2), dtype=np.intp),
        1e-7,
        np.empty((1, 1, 1)),
    )
