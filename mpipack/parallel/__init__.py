"""The parallel layer: no physics. The spatial partition (``domain``), the four communication
verbs and their buffers (``comm``), exact rank-count-independent sums (``exactsum``,
``reduction``), the typed arrays of one rank (``state``) and the cell lists and pair rows
(``neighbors``). Only ``comm`` imports mpi4py; ``exactsum`` and ``neighbors`` are numba code that
the kernels may use."""
