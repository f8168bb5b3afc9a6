"""An independent check of the keep-out code: exact point-to-volume distances, written apart
from :mod:`companion.kinematics.collision` (no segment algorithms), and the clearance of the
arm's capsules by dense sampling along their axes. Used by the tests and ``bench/keepout.py``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from companion.kinematics import rpy_to_matrix
from companion.kinematics.collision import Box, Capsule, Cylinder, KeepOut, Sphere

_DIAGONALS = (("fr", 1, 1), ("rl", -1, -1), ("fl", 1, -1), ("rr", -1, 1))
#: The example config's 450-size X quad (companion/daemon/examples/armbridge.toml; a test holds
#: them equal): body box, four 10" propeller discs, four splayed legs (body FRD, cm).
QUAD_450 = (
    Box("body", (0, 0, -1), (24, 14, 10)),
    *(Cylinder(f"prop_{n}", (15.9 * x, 15.9 * y, -6), 13.0, 2.0) for n, x, y in _DIAGONALS),
    *(Capsule(f"leg_{n}", (9 * x, 9 * y, 4), (13 * x, 13 * y, 24), 1.0) for n, x, y in _DIAGONALS),
)


def point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    dd = float(d @ d)
    t = np.clip(((p - a) @ d) / dd, 0.0, 1.0) if dd > 0 else np.zeros(p.shape[:-1])
    return np.linalg.norm(p - (a + t[..., None] * d), axis=-1)


def _local(p: np.ndarray, center: Sequence[float], rpy_deg: Sequence[float]) -> np.ndarray:
    rot = rpy_to_matrix(*np.radians(rpy_deg))
    return (p - np.asarray(center)) @ rot


def point_distance(p: np.ndarray, v: Box | Capsule | Cylinder | Sphere) -> np.ndarray:
    """Distance (cm) from points ``(..., 3)`` in body FRD to volume ``v``; 0 inside."""
    if isinstance(v, Sphere):
        return np.maximum(np.linalg.norm(p - np.asarray(v.center_cm), axis=-1) - v.radius_cm, 0)
    if isinstance(v, Capsule):
        seg = point_segment(p, np.asarray(v.from_cm), np.asarray(v.to_cm))
        return np.maximum(seg - v.radius_cm, 0)
    if isinstance(v, Box):
        out = np.maximum(np.abs(_local(p, v.center_cm, v.rpy_deg)) - np.asarray(v.size_cm) / 2, 0)
        return np.linalg.norm(out, axis=-1)
    local = _local(p, v.center_cm, v.rpy_deg)
    radial = np.maximum(np.hypot(local[..., 0], local[..., 1]) - v.radius_cm, 0)
    axial = np.maximum(np.abs(local[..., 2]) - v.length_cm / 2, 0)
    return np.hypot(radial, axial)


def sampled_clearance(ko: KeepOut, q: np.ndarray, points: int = 200) -> np.ndarray:
    """Per configuration of ``q`` ``(S, n)``: the least (distance − capsule radius) over
    ``points`` samples along every link capsule's axis and every volume (cm)."""
    seg = ko.segments(np.atleast_2d(q))  # (S, C, 2, 3)
    u = np.linspace(0.0, 1.0, points)[:, None]
    pts = seg[:, :, None, 0] + u * (seg[:, :, None, 1] - seg[:, :, None, 0])  # (S, C, U, 3)
    worst = np.full(seg.shape[0], np.inf)
    for v in ko.volumes:
        d = point_distance(pts, v).min(axis=2) - ko.radii_cm  # (S, C)
        worst = np.minimum(worst, d.min(axis=1))
    return worst
