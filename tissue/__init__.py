"""probegym's finite-element tissue simulator.

Knows nothing of MuJoCo, Gymnasium or torch: a scriptable hyperelastic tet simulator with
implicit integration, sparse solvers, probe contact strategies and a PBD baseline.
"""
