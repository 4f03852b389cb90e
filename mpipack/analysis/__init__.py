"""Analysis of scenes before a run: the stability check (``check``, ``stability``) and the
memory footprint (``footprint``). Post-processing of a run's files is ``mpipack.post``."""
