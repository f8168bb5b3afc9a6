"""Keep-out checks: distances against brute force, and the safety properties against an
independent dense sampling (point-to-volume distances written here, not the module's)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.kinematics import collision_kernels
from companion.kinematics.arm import Arm
from companion.kinematics.collision import (
    Box,
    Capsule,
    Collision,
    Cylinder,
    KeepOut,
    Sphere,
    check_configuration,
    check_motion,
    segment_box_distance,
    segment_segment_distance,
)
from companion.kinematics.vehicle import Mount
from devkit.keepout import QUAD_450, point_segment, sampled_clearance

ARM = Arm.default()
MOUNT = Mount()
QUAD = QUAD_450
PARK = np.radians([0, 90, 0, 0, 0, 0])


# -- distances ------------------------------------------------------------------------------------


def test_segment_segment_distance_golden_cases():
    o = np.zeros(3)
    x = np.array([1.0, 0, 0])
    cases = [
        ((o, x, np.array([0.5, 1, -1]), np.array([0.5, 1, 1])), 1.0),  # skew, crossing above
        ((o, x, np.array([2.0, 0, 0]), np.array([3.0, 0, 0])), 1.0),  # collinear, apart
        ((o, x, np.array([0.0, 2, 0]), np.array([1.0, 2, 0])), 2.0),  # parallel
        ((o, o, np.array([3.0, 4, 0]), np.array([3.0, 4, 0])), 5.0),  # two points
        ((o, x, np.array([0.5, 0, 0]), np.array([0.5, 0, 0])), 0.0),  # point on the segment
        ((o, x, np.array([0.5, -1, 0]), np.array([0.5, 1, 0])), 0.0),  # crossing
    ]
    for (p1, q1, p2, q2), expected in cases:
        assert segment_segment_distance(p1, q1, p2, q2) == pytest.approx(expected, abs=1e-12)
        assert segment_segment_distance(p2, q2, p1, q1) == pytest.approx(expected, abs=1e-12)


def test_segment_distances_match_brute_force():
    rng = np.random.default_rng(18)
    n = 400
    p0, p1 = rng.uniform(-5, 5, (n, 3)), rng.uniform(-5, 5, (n, 3))
    p1[:40] = p0[:40]  # some points
    a, b = rng.uniform(-5, 5, (n, 3)), rng.uniform(-5, 5, (n, 3))
    half = rng.uniform(0.1, 3, (n, 3))
    t = np.linspace(0, 1, 2001)[:, None, None]
    pts = p0 + t * (p1 - p0)  # (T, n, 3)
    brute_box = np.linalg.norm(np.maximum(np.abs(pts) - half, 0), axis=-1).min(axis=0)
    exact_box = segment_box_distance(p0, p1, half)
    step = np.linalg.norm(p1 - p0, axis=-1) / 2000
    assert np.all(exact_box <= brute_box + 1e-9)  # never more than a point's true distance
    assert np.all(exact_box >= brute_box - step - 1e-9)  # and exact up to the sampling
    brute_seg = np.stack([point_segment(pts[:, i], a[i], b[i]).min() for i in range(n)])
    exact_seg = segment_segment_distance(p0, p1, a, b)
    assert np.all(exact_seg <= brute_seg + 1e-9)
    assert np.all(exact_seg >= brute_seg - step - 1e-9)


def test_compiled_clearances_equal_the_reference():
    rng = np.random.default_rng(12)
    volumes = (
        *QUAD,
        Sphere("ball", (30, 0, 30), 5),
        Box("tilted", (0, 30, 30), (5, 9, 14), (10, 20, 30)),
    )
    ko = KeepOut(ARM, volumes, Mount((1, 2, 3), (10, -20, 30)), 1.0)
    q = ARM.random_q_rad(rng, 200)
    np.testing.assert_allclose(ko.clearances(q), ko.clearances_reference(q), rtol=0, atol=1e-9)
    stanford = Arm.from_package_file("stanford.toml")  # a prismatic joint
    shaped = dataclasses.replace(stanford, link_shapes=((), *ARM.link_shapes[1:]))
    ko = KeepOut(shaped, volumes, MOUNT, 1.0)
    q = stanford.random_q_rad(rng, 100)
    np.testing.assert_allclose(ko.clearances(q), ko.clearances_reference(q), rtol=0, atol=1e-9)


# -- the shipped quad ------------------------------------------------------------------------------


def test_park_is_clear_and_pointing_up_hits_the_body():
    ko = KeepOut(ARM, QUAD, MOUNT, margin_cm=1.0)
    assert ko.check(PARK) is None
    hit = ko.check(np.radians([0, 180, 0, 0, 0, 0]))  # straight up, into the body
    assert isinstance(hit, Collision) and (hit.link, hit.volume) == ("q2", "body")
    assert hit.clearance_cm < 0 and hit.proven
    # Swinging the outstretched arm 45° to the right puts the upper arm through the leg there.
    hit = ko.check(np.radians([45, 90, 0, 0, 0, 0]))
    assert hit is not None and (hit.link, hit.volume) == ("q2", "leg_fr")


def test_margin_and_mount_move_the_verdict():
    q = np.radians([30, 90, 0, 0, 0, 0])  # the upper arm passes 3.5 cm from the front-right leg
    clear = sampled_clearance(KeepOut(ARM, QUAD, MOUNT), q)[0]
    assert 0 < clear < 1.0  # within the 1 cm margin, outside the leg
    assert check_configuration(ARM, q, QUAD, MOUNT, margin_cm=1.0) is not None
    assert check_configuration(ARM, q, QUAD, MOUNT, margin_cm=0.0) is None
    low = Mount(xyz_cm=(0.0, 0.0, 30.0))  # 30 cm down: under the legs' feet (24 cm)
    assert check_configuration(ARM, np.radians([45, 90, 0, 0, 0, 0]), QUAD, low) is None


def test_bad_input_names_the_field():
    with pytest.raises(ValueError, match=r"Sphere.radius_cm"):
        Sphere("s", (0, 0, 0), -1.0)
    with pytest.raises(ValueError, match=r"Box.size_cm\[2\]"):
        Box("b", (0, 0, 0), (1, 1, 0))
    with pytest.raises(ValueError, match=r"Cylinder.center_cm\[1\]"):
        Cylinder("c", (0, math.nan, 0), 1, 1)
    with pytest.raises(ValueError, match="named 'x'"):
        KeepOut(ARM, [Sphere("x", (0, 0, 0), 1), Sphere("x", (1, 0, 0), 1)])
    with pytest.raises(ValueError, match="margin_cm"):
        KeepOut(ARM, QUAD, margin_cm=-1)
    with pytest.raises(ValueError, match="no link shapes"):
        KeepOut(Arm.from_package_file("ur5.toml"), QUAD)
    with pytest.raises(ValueError, match="q_rad"):
        KeepOut(ARM, QUAD).check([0.0] * 5)


def test_no_volumes_accepts_everything():
    ko = KeepOut(Arm.from_package_file("ur5.toml"), [])
    assert ko.check(np.zeros(6)) is None and ko.check_motion(np.zeros(6), np.ones(6)) is None


# -- properties against the independent sampling --------------------------------------------------

_coord = st.floats(-60, 60)
_size = st.floats(0.2, 30)
_angle = st.floats(-180, 180)
_point = st.tuples(_coord, _coord, st.floats(-20, 80))
_rpy = st.tuples(_angle, _angle, _angle)
_volume = st.one_of(
    st.builds(Sphere, st.just("s"), _point, _size),
    st.builds(Capsule, st.just("c"), _point, _point, _size),
    st.builds(Box, st.just("b"), _point, st.tuples(_size, _size, _size), _rpy),
    st.builds(Cylinder, st.just("y"), _point, _size, st.floats(0.1, 10), _rpy),
)
_volumes = st.lists(_volume, min_size=1, max_size=3).map(
    lambda vs: [dataclasses.replace(v, name=f"v{i}") for i, v in enumerate(vs)]
)
_unit = st.lists(st.floats(0, 1), min_size=6, max_size=6)
_mount = st.builds(Mount, st.tuples(_coord, _coord, _coord), _rpy)


def _q(unit):
    return ARM.lower_q + np.asarray(unit) * (ARM.upper_q - ARM.lower_q)


@settings(max_examples=40)
@given(volumes=_volumes, unit=_unit, mount=_mount, margin=st.floats(0, 3))
def test_an_accepted_configuration_is_clear_by_dense_sampling(volumes, unit, mount, margin):
    ko = KeepOut(ARM, volumes, mount, margin)
    q = _q(unit)
    if ko.check(q) is None:
        assert sampled_clearance(ko, q)[0] >= margin - 1e-9


def test_accepted_configurations_are_clear_in_bulk():
    """The same property over 500 random configurations against the quad and a cloud of
    volumes, in one batch; and for exact shapes the checker refuses no more than needed (a
    sampled clearance above the margin + the sampling gap is accepted)."""
    rng = np.random.default_rng(1818)
    q = ARM.random_q_rad(rng, 500)
    cloud = [
        Sphere("ball", (30, 10, 30), 8),
        Box("crate", (0, -30, 40), (10, 20, 15), (10, 20, 30)),
        Cylinder("disc", (35, 0, 10), 10, 0.5, (0, 60, 0)),
    ]
    for volumes in (QUAD, cloud):
        ko = KeepOut(ARM, volumes, MOUNT, 1.0)
        accepted = ko.clear_mask(q)
        sampled = sampled_clearance(ko, q, points=100)
        assert np.all(sampled[accepted] >= 1.0 - 1e-9)
        assert 0.2 < accepted.mean() < 0.98  # both verdicts are exercised
    exact = KeepOut(ARM, cloud[:2], MOUNT, 1.0)
    sampled = sampled_clearance(exact, q, points=100)
    gap = 30.2 / 99 / 2  # half the longest capsule's sampling step bounds the sampling error
    assert np.all(exact.clear_mask(q)[sampled >= 1.0 + gap])


@settings(max_examples=20)
@given(volumes=_volumes, a=_unit, b=_unit, margin=st.floats(0, 2))
def test_an_accepted_motion_is_clear_by_dense_sampling(volumes, a, b, margin):
    ko = KeepOut(ARM, volumes, MOUNT, margin)
    q0, q1 = _q(a), _q(b)
    if ko.check_motion(q0, q1) is None:
        s = np.linspace(0, 1, 301)[:, None]
        assert sampled_clearance(ko, q0 + s * (q1 - q0), points=60).min() >= margin - 1e-9


def test_a_thin_disc_between_samples_is_found():
    """A 0.05 mm disc across the path of the hand, at a point between any samples a fixed
    step would take, with both ends of the motion well clear: refused."""
    q0 = np.radians([-60, 90, 0, 0, 0, 0])
    q1 = np.radians([60, 90, 0, 0, 0, 0])
    ko0 = KeepOut(ARM, QUAD[:1], MOUNT, 0.0)
    s = 0.4321
    hand = ko0.segments((q0 + s * (q1 - q0))[None])[0, -1, 1]  # the hand point at s
    disc = Cylinder("thin", tuple(hand), 3.0, 0.005, (90, 0, 0))  # upright, across the sweep
    ko = KeepOut(ARM, [disc], MOUNT, 0.0)
    assert ko.check(q0) is None and ko.check(q1) is None
    hit = ko.check_motion(q0, q1)
    assert hit is not None and hit.volume == "thin" and 0.3 < hit.fraction < 0.6
    # From a single interval (no sampling density to lean on), the speed bound alone finds it.
    hit = KeepOut(ARM, [disc], MOUNT, 0.0, step_cm=1e9).check_motion(q0, q1)
    assert hit is not None and hit.volume == "thin" and 0.3 < hit.fraction < 0.6
    assert KeepOut(ARM, [disc], MOUNT, 0.0).check_motion(q0, q0) is None


@pytest.mark.parametrize("name", ["paper_arm.toml", "stanford.toml"])
def test_the_speed_bound_holds(name):
    """No point of any capsule moves faster than the bound, on random motions (finite
    differences of the capsules' end points: the farthest points from every axis). Stanford:
    a prismatic joint, with the papers' link shapes borrowed."""
    arm = Arm.from_package_file(name)
    arm = dataclasses.replace(arm, link_shapes=((), *ARM.link_shapes[1:]))
    rng = np.random.default_rng(7)
    ko = KeepOut(arm, QUAD, MOUNT)
    for _ in range(10):
        q0, q1 = arm.random_q_rad(rng, 2)
        s = np.linspace(0, 1, 1001)[:, None]
        seg = ko.segments(q0 + s * (q1 - q0))  # (S, C, 2, 3)
        speed = np.linalg.norm(np.diff(seg, axis=0), axis=-1).max(axis=(0, 2)) * 1000
        assert np.all(speed <= ko.speeds(q0, q1) * (1 + 1e-9))


def test_a_grazing_motion_is_refused_as_unproven():
    # The margin is met exactly at the middle of the motion: the bound cannot prove it.
    q0, q1 = np.radians([-20, 90, 0, 0, 0, 0]), np.radians([20, 90, 0, 0, 0, 0])
    ko0 = KeepOut(ARM, [Sphere("p", (80.0, 0.0, 0.0), 1.0)], MOUNT, 0.0)
    least = ko0.clearances(q0[None] + np.linspace(0, 1, 2001)[:, None] * (q1 - q0)).min()
    margin = float(least) - 1e-6
    ko = KeepOut(ARM, [Sphere("p", (80.0, 0.0, 0.0), 1.0)], MOUNT, margin, max_depth=4)
    hit = ko.check_motion(q0, q1)
    assert hit is not None and hit.volume == "p" and not hit.proven
    assert check_motion(ARM, q0, q1, ko.volumes, MOUNT, float(least) - 0.5) is None


def test_warm_up_compiles_the_one_specialisation_the_checks_use():
    # A read-only or differently typed array would make numba compile (~10 s) a second time.
    collision_kernels.warm_up()
    KeepOut(ARM, QUAD, MOUNT).check(PARK)
    assert len(collision_kernels.clearances.signatures) == 1


# -- polylines (a control step's outputs changing one after another) ------------------------------


def test_check_path_refuses_a_corner_the_straight_motion_misses():
    # From q to q + (20, 20) deg on q1 and q2: the straight line is clear of a ball put on the
    # corner (q1 moved, q2 not yet), which the outputs pass when the commands land in order.
    ko0 = KeepOut(ARM, (), MOUNT)
    q0 = ARM.q_from_user([0, 60, 0, 0, 0, 0])
    q1 = ARM.q_from_user([20, 80, 0, 0, 0, 0])
    corner = ARM.q_from_user([20, 60, 0, 0, 0, 0])
    hand = ko0.segments(corner[None])[0, -1, 1]  # the hand's end at the corner (body FRD)
    ko = KeepOut(ARM, (Sphere("ball", tuple(hand), 2.0),), MOUNT, 1.0)
    assert ko.check(q0) is None and ko.check(q1) is None
    assert ko.check_motion(q0, q1) is None
    hit = ko.check_path([q0, corner, q1])
    assert hit is not None and hit.volume == "ball"


@settings(max_examples=30)
@given(seed=st.integers(0, 2**32))
def test_check_path_agrees_with_check_motion_leg_by_leg(seed):
    rng = np.random.default_rng(seed)
    ko = KeepOut(ARM, QUAD, MOUNT, 1.0)
    start = ARM.random_q_rad(rng, 1)[0]
    legs = np.cumsum(rng.uniform(-1, 1, (4, ARM.dof)) * np.radians(6), axis=0) + start
    path = np.clip(np.vstack([start, legs]), ARM.lower_q, ARM.upper_q)
    each = [ko.check_motion(a, b) for a, b in zip(path[:-1], path[1:], strict=True)]
    assert (ko.check_path(path) is None) == all(h is None for h in each)
