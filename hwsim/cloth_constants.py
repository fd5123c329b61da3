"""The truth cloth solver's fixed constants (hwsim/cloth.py), each with why it has its value."""

GRAVITY_M_S2 = 9.81
# Laying a cloth with ridges down, and hands letting go of one: quasi-static (velocity decays within
# 10 ms) until its ridges have settled.
LAY_IN_S = 0.5
LAY_IN_DAMPING_1_S = 100.0
ON_TABLE_M = 1e-4  # a node laid lower than this (above its floor) rests on the table
# How much shorter than the other a cell's diagonal must be to count as the one a fold crosses: the
# choice only matters in a cell that is not flat, and any value from 1e-5 to 1e-3 held the same ridges.
FOLD_STRAIN = 1e-4
# A cell whose diagonals' midpoints lie closer than this (of the diagonal) is flat: its diagonals' lengths
# along the cloth are their straight ones, to 1e-6 (the difference goes as the square).
FLAT_CELL = 1e-3
# The yarns' frictional element sticks with this stiffness (k_f / B) until its couple reaches HB, i.e. for
# a change of curvature of HB / k_f (11 m⁻¹ for the default cloth): Grosberg's friction is rigid until it
# slips; 20 made the Gauss–Seidel solve blow up at 0.5 ms substeps.
YARN_FRICTION_STIFFNESS = 4.0
# A belt this fast shakes the cloth with the full vibration_m_s; slower belts proportionally less.
VIBRATION_REF_SPEED_M_S = 0.05
