"""The finite elements: per-region hyperelastic materials (:mod:`tissue.fem.material`), the
elastic energy, forces and tangents of a tet mesh (:mod:`tissue.fem.elasticity`) and the
compiled element kernels behind them (:mod:`tissue.fem.kernels`)."""
