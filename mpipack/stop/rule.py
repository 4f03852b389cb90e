"""The stop rule: what ends a run, asked once per iteration by the loop (``engine.loop``).

After iteration n + 1 (figures ``fig``, reduced, the same on every rank), in this order:

    hook          a hook returned ``engine.hooks.STOP`` (e.g. the wall-time limit)   -> its name
    signal        SIGTERM, SIGUSR1 or SIGINT on any rank (``engine.signals``)          "signal"
    max_seconds   the loop's wall clock reached stop.max_seconds (> 0)                 "max_seconds"
    certified     every stop.check_every iterations, the certificate holds
                  (``stop.certificate``; stops under stop.rule = "certified" and
                  "jammed")                                                            "certified"
    jammed        under stop.rule = "jammed", after every iteration: max overlap <=
                  stop.overlap and |W^n - W^{n-w}| / W^n <= stop.jammed_rtol over
                  w = max(the certificate's window, JAMMED_MIN_WINDOW) iterations     "jammed"
    eps           under stop.rule = "eps" (stop.eps > 0): the paper's (4.3),
                  ||X^{n+1} - X^n|| / ||X^n|| < eps                                    "eps"
    watchdog      at a block's end, numerical trouble (``stop.watchdog``): raises
                  ``errors.NumericalError``
    max_iter      the run has made stop.max_iter iterations                            "max_iter"

Every input is a reduced value, so every rank stops on the same iteration. "converged" is a
separate verdict (``final``): the final state meets the certificate, whatever stopped the loop.

The jammed finish (``stop.rule = "jammed"``) is a packing, not a certified one: the overlap
criterion of the certificate, and W settled to a looser tolerance (default 1e-3, ten times
the certificate's) over the certificate's own window (a tenth of the run), at least
JAMMED_MIN_WINDOW iterations. The KKT residual is not required. Both criteria are free (they
come with the iteration's reduction, of X^n), so they are tested after every iteration, not
only at the certificate's checks; when they hold, one metrics pass (about an iteration's cost,
as a certificate check's) measures the state the run would end on, X^{n+1}: its overlap must
hold too, and its KKT residual (the run's own multipliers, no multiplier fit, which can cost a
fifth of the run's time) is the one reported. When that pass finds the overlap above the
tolerance, the next iteration's free test (of that same X^{n+1}) fails: at most one pass for
two iterations. The rule's only state is the certifier's W history, which keeps the longer of
the two windows and travels in checkpoints. Measured with the fire-al schedule
(docs/benchmarks.md, "Jammed finish"), W is within 1e-3 of its final value long before the
overlap reaches stop.overlap, so the overlap decides the stop, and it dips below the tolerance
between two checks of the certificate: 3D N = 1e4 seeds 1 - 4 jammed 2350, 1900, 2050 and
2150 iterations at the checks every 50, and 1774, 1893, 1884 and 1784 when tested after every
iteration, each W still below LAMMPS's two-stage quench's on the same start. On
traces of every iteration, windows of a twentieth of the run or of 50, 200 or 500 iterations
stop 3D N = 2000 and N = 1e4 on the same check as a tenth; in 2D (default scene) 50 or 200
iterations stop one check sooner (2300 against 2350; certified 3100), 500 iterations later
(2750), and a fiftieth of the run (1 iteration at iteration 50) was fooled at iteration 50
(W 6x its final value, the cloud still expanding). The floor of JAMMED_MIN_WINDOW iterations
keeps a start at rest from passing the test early: with the window at least stop.check_every
(the floor before), stop.check_every = 10 stopped 3D N = 1e4 "jammed" at iteration 30, the
spread cloud at rest at 6 times its final W.

A signal that arrives during a certificate check's multiplier fit ends the fit on every rank
(``stop.signals.Interrupted``) and the run at once: the check is kept as pending in the
checkpoint, and a restart makes it first, before its first iteration, then takes the rest of
that iteration's decisions: the same decisions as a run never stopped.
"""

import math

from mpipack.errors import NumericalError
from mpipack.stop import watchdog as watchdog_mod
from mpipack.stop.certificate import Certifier
from mpipack.stop.signals import Interrupted

# the jammed rule's shortest window of W (see the module docstring)
JAMMED_MIN_WINDOW = 100


class StopRule:
    """The scene's ``stop`` section as one decision per iteration; its state (the certifier's
    W history and fit budget, the watchdog's blocks) travels in checkpoints (``save``)."""

    def __init__(self, scene, solver, saved=None):
        self.stop = scene.stop
        # the rules that stop on a certificate: "eps" runs on to (4.3), as the paper's
        self.certified_rule = self.stop.rule in ("certified", "jammed")
        self.jammed_rule = self.stop.rule == "jammed"
        self.certifier = Certifier(self.stop, keep=JAMMED_MIN_WINDOW if self.jammed_rule else 0)
        self.jammed = None  # the jammed criteria of the test that stopped the run
        self.watchdog = make_watchdog(solver, scene)
        self.pending = None  # the figures of an iteration whose check a signal cut short
        if saved:  # a restart: the same decisions as the run it continues
            if "certifier" in saved:
                self.certifier.restore(saved["certifier"])
            if self.watchdog is not None and "watchdog" in saved:
                self.watchdog.restore(saved["watchdog"])
            self.pending = saved.get("pending_check")

    def before(self, solver):
        """The reason not to start an iteration at all, or None: a check that a signal cut short
        (made now, with the rest of its iteration's decisions), or a restart at its bound."""
        if self.pending is not None:
            fig, self.pending = dict(self.pending), None
            reason = self._from_check(solver, fig)
            if reason is not None:
                return reason
        return "max_iter" if solver.state.iteration >= self.stop.max_iter else None

    def decide(self, solver, fig, hook=None):
        """The reason to stop after this iteration (see the module docstring), or None.
        ``hook``: the name of a hook that asked to stop."""
        stop, it = self.stop, fig["iteration"]
        self.certifier.record(it - 1, fig["W"])  # W^n comes with iteration n + 1
        reason = hook
        if reason is None and fig.get("stop_request"):
            reason = "signal"
        if reason is None and stop.max_seconds > 0 and fig["wall"] >= stop.max_seconds:
            reason = "max_seconds"  # the wall clock is reduced: collective
        return reason if reason is not None else self._from_check(solver, fig)

    def _from_check(self, solver, fig):
        """The decisions of an iteration from its certificate check on."""
        stop, it = self.stop, fig["iteration"]
        reason = None
        if it % stop.check_every == 0:
            try:
                if self.certifier.check(solver, fig) and self.certified_rule:
                    reason = "certified"
            except Interrupted:  # the check is made again by the run that continues this one
                self.pending = {k: v for k, v in fig.items()}
                return "signal"
        if reason is None and self.jammed_rule and self._jammed(solver, fig):
            reason = "jammed"
        if reason is None and stop.rule == "eps" and stop.eps > 0 and fig["relative_change"] < stop.eps:
            reason = "eps"
        if reason is None and self.watchdog is not None:
            self._watch(solver, fig)
        if reason is None and it >= stop.max_iter:
            reason = "max_iter"
        return reason

    def jammed_window(self, iteration):
        """The jammed rule's window in iterations at iteration n: the certificate's (a fraction
        stop.w_window of the run), at least JAMMED_MIN_WINDOW."""
        return max(self.certifier.window(iteration), JAMMED_MIN_WINDOW)

    def _jammed(self, solver, fig):
        """True when the state after this iteration is jammed (see the module docstring). The
        free test first: max overlap and W's change over the jammed window, from this
        iteration's reduction (of X^n); when it passes, the overlap of X^{n+1} itself, the state
        the run would end on, from one metrics pass (``Certifier.measured``, which also gives the
        KKT residual of the stop). Every input is reduced (collective). The figures of a
        passing test are kept in ``jammed``."""
        it = fig["iteration"] - 1  # fig["W"] is W^n, as in the certificate's check
        window = self.jammed_window(it)
        w_change = self.certifier.w_change(it, fig["W"], window)
        if not (fig["max_overlap"] <= self.stop.overlap and w_change <= self.stop.jammed_rtol):
            return False
        crit = self.certifier.measured(solver, fig["iteration"])
        if not crit["overlap"]["ok"]:
            return False
        self.jammed = {"iteration": fig["iteration"], "max_overlap": crit["overlap"]["value"],
                       "overlap_tol": self.stop.overlap, "w_change": w_change,
                       "w_rtol": self.stop.jammed_rtol, "window": window,
                       "kkt_residual": crit["kkt"]["value"], "kkt_required": False}
        return True

    def _watch(self, solver, fig):
        """Feed the watchdog one iteration's figures; at a block's end, its verdict raised as a
        NumericalError (collective: every input is reduced)."""
        wd = self.watchdog
        wd.observe(fig)
        it = fig["iteration"]
        if not wd.due(it):
            return
        last = self.certifier.last
        kkt = last["criteria"]["kkt"]["value"] if last and it - last["iteration"] < watchdog_mod.BLOCK else math.nan
        verdict = wd.block_end(it, solver.max_lambda(), self.certifier.w_change(it - 1, fig["W"]), kkt)
        if verdict is not None:
            kind, message = verdict
            raise NumericalError(message, solver, kind)

    def final(self, solver, final_fig, reason):
        """The certificate of the final state (``stop.certificate.Certifier.final``). A run
        stopped by a signal or its wall time is about to be ended by its scheduler: no
        multiplier fit (seconds to minutes at large N), the run's own multipliers. Nor a jammed
        stop (asked to be quick): the check of its iteration's, when one was made, else the
        run's own multipliers."""
        fit = reason not in ("signal", "walltime", "jammed")
        fired = reason in ("certified", "jammed")
        try:
            return self.certifier.final(solver, solver.state.iteration, final_fig, fired, fit=fit)
        except Interrupted:  # a signal during the final fit: the run's own multipliers
            return self.certifier.final(solver, solver.state.iteration, final_fig, fired, fit=False)

    def save(self):
        """The rule's state for a checkpoint (JSON-able; keys of the checkpoint's ``extra``)."""
        out = {"certifier": self.certifier.save()}
        if self.watchdog is not None:
            out["watchdog"] = self.watchdog.save()
        if self.pending is not None:
            out["pending_check"] = {k: (v.item() if hasattr(v, "item") else v) for k, v in self.pending.items()}
        return out


def make_watchdog(solver, scene):
    """The run's ``Watchdog`` (None with stop.watchdog = false). Its no-progress test is for
    the methods whose failure is a cycle or a wander (``Method.watch_stall``: the paper's
    methods as given), and off when the scene asked for a fixed number of iterations
    (stop.rule "eps", stop.eps = 0)."""
    stop = scene.stop
    if not stop.watchdog:
        return None
    from mpipack.methods.fire_al_schedule import scene_law
    method = solver.method
    law = scene_law(scene)
    return watchdog_mod.Watchdog(solver.n, solver.r_natural, law["lam_bar"] / method.kkt_lambda_scale,
                                 stop.overlap,
                                 stall=method.watch_stall and not (stop.rule == "eps" and stop.eps == 0),
                                 advice=method.advice())
