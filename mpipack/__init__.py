"""mpipack: MPI-parallel sphere packing with the damped Arrow-Hurwicz algorithm."""
__version__ = "0.1.0"
