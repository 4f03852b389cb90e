"""The stop rule that certifies a packing (``stop.rule = "certified"``), and the certificate
reported at the end of every run, whatever its rule.

A configuration X is certified when, together:

    overlap   max over pairs (d_kl - |X_k - X_l|) / d_kl        <= stop.overlap
    kkt       ||grad W + sum lambda grad phi|| / ||grad W||       <= stop.kkt
              for some multipliers lambda >= 0 on the pairs in contact to stop.overlap
              (stationarity of the Lagrangian, (2.4), relative to the pull of W)
    settled   |W^n - W^{n-w}| / W^n                             <= stop.w_rtol
              over the last w = max(1, stop.w_window * n) iterations (a fraction of the
              run: W must have stopped moving on the run's own time scale)

The overlap at X^n and W^n come with every iteration's reduction (free); the KKT residual
needs a metrics pass (``measures.measure``, about the cost of one iteration), so it runs only
every stop.check_every iterations and only when the two free criteria already hold. The
multipliers in the residual are first the run's own for the current X ((2.10b) applied on the
fly for DAHA, the force multipliers under fire-al); when those leave it above stop.kkt, the
best multipliers >= 0 on the pairs in contact are fitted (``fit``: the residual of X itself,
min over m >= 0), when the run's residual is within FIT_GAIN times the tolerance and as long as
the fits have cost at most FIT_SHARE of the run's iterations. Neither changes anything in the
state: the trajectory does not depend on the checks.

The paper's rule (4.3), ``stop.rule = "eps"``, stops on the relative change alone; the
certificate is then evaluated at the stop and reported, and "converged" is true only if it
holds.
"""

import collections
import math

from mpipack.stop import measures

MIN_WINDOW = 1
# the multiplier fits of the checks cost at most FIT_SHARE of the run's iterations, a fit step
# counted as FIT_STEP_COST iterations (two passes over the pairs in contact, a ghost refresh and
# one allreduce cost 0.88 - 1.09 iterations when the count was set, and since the fit's kernels
# run over the contacts alone 0.34 of an iteration of the loop at 3D N = 2000, 0.24 at 3D N =
# 8000, 0.30 there on 2 ranks, 0.43 at 2D N = 32000; about one iteration of a packed state since
# the passes became cheaper and the fit's kernels were compiled per dimension, docs/benchmarks.md
# session 44; counting a step as 0.35 iteration certified 3D N = 2000 5.5% sooner in iterations, but
# where the extra fits failed they cost time for nothing: docs/research/convergence.md, section 3p), and
# a check fits only when the run's multipliers leave the KKT residual within FIT_GAIN times its
# tolerance (the fit removed at most 20x of it where it certified: docs/research/convergence.md, section
# 3h) and the budget left allows at least FIRST_FIT_STEPS steps for a run's first fit,
# MIN_FIT_STEPS for every later one (250 certifies short runs, a fifth of 1250 - 2500
# iterations, by a fit: section 3n; but once the budget is spent, 250-step fits left 3D N = 1e5
# uncertified at 93000 iterations where 500 had certified it: section 3m); a fit takes at most
# the budget left (one long fit gets further than several short ones, each of which starts again
# from the run's multipliers: section 3l)
FIT_SHARE, FIT_STEP_COST, FIT_GAIN, MIN_FIT_STEPS, FIRST_FIT_STEPS = 0.2, 1.0, 20.0, 500, 250


class Certifier:
    """Tracks W over the run and decides whether the current state is certified (collective:
    every input is a reduced value)."""

    def __init__(self, stop, keep=0):
        self.stop = stop
        # the history also reaches ``keep`` iterations back when that is longer than the window
        # (the jammed rule's window, ``stop.rule``: one history for both)
        self.keep = keep
        self.w_history = collections.deque()  # (iteration, W^n), every iteration
        self.last = None  # the last full check
        self.fit_steps = 0  # multiplier-fit steps of the checks so far

    def window(self, iteration):
        return max(MIN_WINDOW, math.ceil(self.stop.w_window * iteration))

    def record(self, iteration, w):
        """W^n of every iteration (free: it comes with the iteration's reduction, which sums
        |X^n|^2 while it makes X^{n+1}: figures of iteration n+1 carry W^n)."""
        self.w_history.append((iteration, w))
        # the window only grows forward: older records than the current target are not needed
        target = iteration - max(self.window(iteration), self.keep)
        while len(self.w_history) > 1 and self.w_history[1][0] <= target:
            self.w_history.popleft()

    def w_change(self, iteration, w, window=None):
        """|W^n - W^{n-w}| / W^n, W^{n-w} the latest record at least a window old; inf while
        the run is younger than its window. ``window``: iterations, at most
        max(``window(iteration)``, ``keep``) (default: the certificate's)."""
        target = iteration - (self.window(iteration) if window is None else window)
        h = self.w_history
        if not h or h[0][0] > target:
            return math.inf
        k = 0  # the latest record at least a window old (a read: ``record`` prunes)
        while k + 1 < len(h) and h[k + 1][0] <= target:
            k += 1
        old = h[k][1]
        if w == old:  # also W = 0 throughout (one sphere, or nothing to pull together)
            return 0.0
        if not (w > 0):
            return math.inf
        return abs(w - old) / w

    def save(self):
        """The state a restart needs to take the same decisions (JSON-able)."""
        return {"w_history": [[int(i), float(w)] for i, w in self.w_history],
                "fit_steps": self.fit_steps}

    def restore(self, saved):
        self.w_history = collections.deque((int(i), float(w)) for i, w in saved["w_history"])
        self.fit_steps = int(saved.get("fit_steps", 0))

    def criteria(self, overlap, kkt, w_change):
        """{name: {"value", "tol", "ok"}} for the three criteria."""
        st = self.stop
        out = {"overlap": {"value": overlap, "tol": st.overlap},
               "kkt": {"value": kkt, "tol": st.kkt},
               "settled": {"value": w_change, "tol": st.w_rtol}}
        for c in out.values():
            c["ok"] = bool(c["value"] <= c["tol"])
        return out

    def check(self, solver, fig):
        """Every check_every iterations: when the free criteria hold, run the metrics pass
        (and, within the fits' budget, the multiplier fit). Returns True when the state is
        certified."""
        it = fig["iteration"] - 1  # fig["W"] is W^n, of the positions the step started from
        w_change = self.w_change(it, fig["W"])
        if not (fig["max_overlap"] <= self.stop.overlap and w_change <= self.stop.w_rtol):
            return False
        # all three criteria of one configuration: the current X^{n+1}, its W and its iteration
        # (the certificate at the end of the run is of that same state)
        m, _ = measures.measure(solver, overlap_a=False)
        now = fig["iteration"]
        budget = int((FIT_SHARE * now - FIT_STEP_COST * self.fit_steps) / FIT_STEP_COST)
        least = MIN_FIT_STEPS if self.fit_steps else FIRST_FIT_STEPS
        fit = budget >= least and m["kkt_residual"] <= FIT_GAIN * self.stop.kkt
        self.last = {"iteration": now,
                     "criteria": self.certificate(solver, now, m, fit=fit, max_steps=budget)}
        return all(c["ok"] for c in self.last["criteria"].values())

    def measured(self, solver, iteration):
        """The criteria of the current state, ``iteration`` its iteration, with the run's own
        multipliers (a metrics pass, no fit), kept as the last check (``final`` reports them);
        the last check's own when one was made at this iteration. Collective."""
        if self.last is None or self.last["iteration"] != iteration:
            m, _ = measures.measure(solver, overlap_a=False)
            self.last = {"iteration": iteration, "criteria": self.certificate(solver, iteration, m, fit=False)}
        return self.last["criteria"]

    def certificate(self, solver, iteration, m, fit=True, max_steps=None):
        """The criteria of the configuration whose ``measure`` figures are m; with ``fit``, the
        KKT residual is the best multipliers' (``measures.best_kkt``, at most max_steps fit
        steps) when the run's own leave it above stop.kkt while the other two criteria hold.
        The kkt entry also says which multipliers gave it ("run" or "fitted") and the run's
        own residual."""
        st = self.stop
        kkt_run = kkt = m["kkt_residual"]
        crit = self.criteria(m["max_overlap"], kkt, self.w_change(iteration, m["W"]))
        multipliers = "run"
        if fit and not crit["kkt"]["ok"] and crit["overlap"]["ok"] and crit["settled"]["ok"]:
            fitted, steps = measures.best_kkt(solver, m, st.kkt, max_steps)
            self.fit_steps += steps
            if fitted < kkt:
                kkt, multipliers = fitted, "fitted"
                crit["kkt"].update(value=kkt, ok=bool(kkt <= st.kkt))
        crit["kkt"].update(multipliers=multipliers, run_value=kkt_run)
        return crit

    def final(self, solver, iteration, final_fig, fired, fit=True):
        """The certificate of the final state (final_fig from ``measures.finish``). When the
        loop stopped on a certified check (``fired``), that check's verdict is the one
        reported: the final figures are of the same configuration. Otherwise the final state
        gets its own, with a multiplier fit whatever the fits' budget (one fit more; none with
        ``fit`` False)."""
        if fired and self.last is not None and self.last["iteration"] == iteration:
            return self.last["criteria"]
        return self.certificate(solver, iteration, final_fig, fit=fit)
