"""What "converged" means and when a run stops: the certificate (``certificate``), the metrics
pass it needs (``measures``), the best multipliers' fit (``fit``) and the watchdog that stops a
run in numerical trouble (``watchdog``)."""
