"""The engine: the loop (``loop.run``), the ``Solver`` that holds one rank's share of the
cloud and its collective operations, rebuilds (``rebuild``), hooks and timers, initial data
(``initial``), and a whole run with its files, signals and summary (``runner``)."""
