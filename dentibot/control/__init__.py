"""Pure mathematics of DentiBot (thesis chapters 3-5).

Nothing here does I/O, uses asyncio, logs, or imports another DentiBot layer: every
function takes arrays and parameters and returns arrays.

Units: lengths mm, public angles deg (radians inside where clearer), forces N, sensor
torques N*m, file torque mNm, time s.
"""
