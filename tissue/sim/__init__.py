"""The FE simulator: time integration (:mod:`tissue.sim.integrator`: the paper's linearised
backward Euler and the robust Newton), the simulator a contact strategy drives
(:mod:`tissue.sim.simulator`), linear solvers (:mod:`tissue.sim.solvers`, MKL Pardiso in
:mod:`tissue.sim.pardiso`) and rotated node frames for sliding constraints
(:mod:`tissue.sim.frames`)."""
