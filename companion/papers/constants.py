"""The papers' numbers, defined once: the test target G, the joint ranges (Table 2), the DE and
MSFLA settings (Tables 4 and 6) and their published results (Tables 5 and 7).

Sources: ``shared/seeds`` (the DE/MSFLA paper; its Tables 2 and 4–7) as distilled in
``shared/spec/papers.md`` §1–4, and paper 001 (the MSFLA paper on the same arm, whose Table 3
is Table 7 rounded). Centimetres and degrees, as printed.
"""

from __future__ import annotations

from companion.kinematics import Pose

TARGET_G = Pose(-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)
"""§5: G = (x, y, z, roll, pitch, yaw) in cm and degrees; unreachable within the Table 2 limits."""

TABLE1_LINK_LENGTHS_CM: tuple[float, ...] = (3.5, 6.5, 28.2, 21.0, 2.5, 7.5, 5.0)
"""Table 1: the arm part's links l0…l6 in cm (J0–J1 … J6–J7), the lengths of the papers'
modified DH table (Table 3: a0 = l0, a1 = l1, a2 = l2, d4 = l3 + l4, a5 = l5, tool l6 along x)."""

TABLE2_RANGES_DEG: tuple[tuple[float, float], ...] = (
    (-90.0, 90.0),
    (0.0, 180.0),
    (-90.0, 90.0),
    (-90.0, 90.0),
    (-90.0, 90.0),
    (-70.0, 90.0),
)
"""Table 2: (min, max) of θ1…θ6 in degrees. The default arm file and the default calibration
carry the same ranges (a test keeps all three equal)."""

# Table 4: DE/rand/1/bin.
DE_F = 0.9
DE_CR = 0.95
# Table 5 test 9, the authors' pick: NP 12, 400 generations.
DE_POP_SIZE = 12
DE_GENERATIONS = 400

# Table 6: MSFLA.
MSFLA_MEMEPLEXES = 3
MSFLA_LEAP_FACTOR = 1.3
# The classic SFLA (Eusuff & Lansey 2003): D = rand·(Θ_b − Θ_w), i.e. a leap factor of 1.
SFLA_CLASSIC_LEAP_FACTOR = 1.0

# DE/MSFLA paper, Table 5: test, population, iterations, J, execution time ms, reached pose.
TABLE5_DE = [
    (1, 6, 250, 4.60464, 247, "(-20.0619, 3.00659, 40.0358, 3.74, -4.49369, 17.5544)"),
    (2, 6, 500, 1.53162, 594, "(-19.56, 2.64638, 39.8767, 0.465805, 13.2258, 13.135)"),
    (3, 8, 600, 1.19735e-5, 861, "(-20, 3, 40, -8.25797e-6, 10, 15)"),
    (4, 8, 800, 3.60207e-7, 1125, "(-20, 3, 40, 2.59552e-8, 10, 15)"),
    (5, 10, 500, 0.000230295, 986, "(-19.99, 3.0001, 40.00001, 4.21087e-5, 10.004, 15)"),
    (6, 10, 750, 1.55363e-7, 1301, "(-20, 3, 40, 1.13202e-7, 10, 15)"),
    (7, 10, 1000, 4.53651e-9, 1917, "(-20, 3, 40, -1.40416e-9, 10, 15)"),
    (8, 12, 250, 0.22408, 567, "(-19.8094, 3.06099, 40.1352, 0.0528143, 10.1526, 15.087)"),
    (9, 12, 400, 0.0004035, 835, "(-20.0001, 3.00003, 40, -0.0006738, 9.999932, 14.9998)"),
    (10, 12, 500, 3.42549e-5, 1146, "(-20, 3, 4, 3.25415e-5, 10, 15)"),
    (11, 20, 500, 0.000828201, 1736, "(-19.9994, 3.00002, 40.0002, 0.000503176, 10.0009, 14.999)"),
    (12, 20, 750, 1.28825e-6, 2628, "(-20, 3, 40, -3.29831e-6, 10, 15)"),
    (13, 30, 500, 0.00107932, 2614, "(-20.0004, 2.99975, 39.999, 0.000577463, 9.999, 15.0007)"),
    (14, 30, 1000, 9.20132e-7, 5255, "(-20, 3, 40, 3.978432e-8, 10, 15)"),
]

# Table 7: test, NP, iN, iM, J, execution time ms, reached pose.
TABLE7_MSFLA = [
    (1, 20, 30, 10, 11.618, 729, "(-15.7365, 5.43, 52.57, 6.63, 12.66, 16.164)"),
    (2, 30, 30, 10, 7.6614, 1045, "(-21.1832, 2.91528, 50.77, -0.201742, 10.0158, 14.8583)"),
    (3, 40, 30, 15, 10.5382, 1685, "(-25.08, 8.56, 46.818, -6.2, 9.6, 5.4251)"),
    # Pitch 8.6258: the other transcription of this paper reads "-2.537.8.6258.14.1301" and
    # paper 001 prints 8.62; the cleaner transcription's "6.258" lost the leading digit.
    (4, 40, 40, 30, 18.4625, 4526, "(-25.2365, 8.34134, 47.591, -2.5378, 8.6258, 14.1301)"),
    (5, 60, 40, 30, 8.2925, 6645, "(-24.4625, 0.04208, 44.589, 1.655, 11.1161, 14.054)"),
    (6, 80, 50, 40, 11.0236, 13540, "(-26.9977, 3.59399, 42.871, -0.0686, 9.816, 15.6762)"),
    (7, 100, 60, 60, 29.7744, 24191, "(-20.0331, 30.03867, 39.9706, -7.709, 3.6786, -0.7192)"),
    (8, 130, 70, 60, 0.151062, 46282, "(-20.09, 2.988, 40.004, 0.20727, 9.642, 14.894)"),
    (9, 170, 60, 50, 0.616846, 40459, "(-20.1505, 2.8357, 40.0911, 0.8872, 10.3554, 16.149)"),
    (10, 200, 90, 40, 0.113833, 57362, "(-19.9268, 3.00718, 39.98, -0.1344, 10.1049, 14.894)"),
    (
        11,
        200,
        100,
        60,
        0.0728863,
        92779,
        "(-20.0018, 2.99737, 39.9906, -0.13745, 10.1506, 14.9178)",
    ),
    (12, 200, 120, 80, 2.76717, 150246, "(-20.4796, 4.15287, 40.4894, 0.80744, 4.08227, 13.7867)"),
    (
        13,
        200,
        200,
        100,
        2.67129,
        318481,
        "(-19.2649, 2.23482, 41.9365, -0.978994, 10.8776, 11.4859)",
    ),
    (14, 250, 90, 40, 0.003134, 69818, "(-19.9995, 3.00023, 39.9998, 0.00495, 10.0061, 14.995)"),
    # z = 10 in both transcriptions of the DE/MSFLA paper; paper 001 prints 40.
    (15, 250, 140, 80, 1.26635, 215027, "(-20, 3, 10, -7.01976e-10, 10, 15)"),
    (
        16,
        250,
        140,
        100,
        4.64762e-9,
        260325,
        "(-20.0982, 2.9671, 40.0008, -1.68742, 6.68997, 13.5741)",
    ),
    (17, 300, 140, 80, 1.01476e-9, 255989, "(-20, 3, 40, 1.16487e-9, 10, 15)"),
    (18, 500, 90, 40, 5.4912e-10, 136888, "(-20, 3, 40, -1.66261e-11, 10, 15)"),
    (19, 500, 200, 100, 3.02894e-15, 681646, "(-20, 3, 40, 3.22962e-15, 10, 15)"),
    (20, 1000, 30, 45, 0.0968137, 95197, "(-20.0305, 3.0454, 40.0451, -0.0037, 10.957, 14.8752)"),
]

# The "Total Error" columns of Tables 5 and 7, by test (the papers do not define it).
TABLE5_TOTAL_ERROR = (
    -8.22166, 1.78975, 8.26589e-6, 6.13326e-7, 0.000677389, 1.13202e-7, -3.13365e-9, -0.001729,
    0.000107144, 0.000107144, 0.00156291, -4.33271e-6, -0.00085163, 3.09732e-8,
)  # fmt: skip
TABLE7_TOTAL_ERROR = (
    29.7156, 12.0878, 19.2097, 18.4625, 8.2925, 11.0236, 29.7744, 0.648529, 2.16791, 0.297961,
    0.378871, 5.81648, 1.93396, 0.0165418, 6.55357, 1.05135e-8, 3.3374e-9, 9.9601e-10,
    1.5664e-14, 0.0255,
)  # fmt: skip

# Paper 001, Table 3, where its reached pose differs from Table 7 by more than rounding:
# test -> (field, paper 001's value, Table 7's value).
PAPER001_TABLE3_DIFFERENCES = {
    4: ("pitch_deg", 8.62, 8.6258),  # the cleaner transcription of Table 7 reads 6.258
    15: ("z_cm", 40.0, 10.0),
}


def parse_pose(text: str) -> Pose:
    """A reached pose as printed in Tables 5 and 7, ``"(x, y, z, roll, pitch, yaw)"`` in cm and
    degrees, as a :class:`Pose`."""
    parts = text.strip().strip("()").split(",")
    try:
        values = [float(part.replace(" ", "")) for part in parts]
    except ValueError as exc:
        raise ValueError(f"not a printed pose (x, y, z, roll, pitch, yaw): {text!r}") from exc
    return Pose.from_sequence(values)
