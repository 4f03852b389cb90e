"""The methods: what one iteration does to the state. One module per family: ``fixed``
(DAHA and AHA with fixed parameters), ``fire_al`` (the parameter-free schedule and its L-BFGS
phase, ``lbfgs``), ``nested`` (NAP and NAV). A method owns its kernels, its coefficients, its
checkpointed state and its requests to the engine; it never calls MPI itself but through the
``Solver``'s collective operations."""
