"""Experiments built on the engine: the paper's reproduction (``mpipack paper``). They drive
``solver.run`` through hooks and options; none iterates the solver itself."""
