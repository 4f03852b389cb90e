"""The methods: what one iteration does to the state. One module per family: ``fixed``
(DAHA and AHA with fixed parameters), ``fire_al`` (the parameter-free schedule and its L-BFGS
phase, ``lbfgs``), ``nested`` (NAP and NAV). A method owns its kernels, its coefficients, its
checkpointed state and its requests to the engine; it never calls MPI itself but through the
``Solver``'s collective operations."""


def for_scene(scene):
    """The method object a scene asks for (``method.name``, ``method.schedule``)."""
    m = scene.method
    if m.nested:
        from mpipack.methods.nested import Nested
        return Nested(scene)
    if m.schedule == "fire-al":
        from mpipack.methods.fire_al import FireAL
        return FireAL(scene)
    from mpipack.methods.fixed import FixedStep
    return FixedStep(scene)
