"""Running solvers: the solver interface, result folders and batch runs."""
