"""The stop rule that certifies a packing (``stop.rule = "certified"``), and the certificate
reported at the end of every run, whatever its rule.

A configuration X with multipliers lambda >= 0 is certified when, together:

    overlap   max over pairs (d_kl - |X_k - X_l|) / d_kl        <= stop.overlap
    kkt       ||grad W + sum lambda grad phi|| / ||grad W||       <= stop.kkt
              (stationarity of the Lagrangian, (2.4), relative to the pull of W)
    settled   |W^n - W^{n-w}| / W^n                             <= stop.w_rtol
              over the last w = max(1, stop.w_window * n) iterations (a fraction of the
              run: W must have stopped moving on the run's own time scale)

The overlap at X^n and W^n come with every iteration's reduction (free); the KKT residual
needs a metrics pass (``measures.measure``, about the cost of one iteration), so it runs only
every stop.check_every iterations and only when the two free criteria already hold. The
multipliers in the residual are those of the current X ((2.10b) applied on the fly for DAHA),
and the pass changes nothing in the state: the trajectory does not depend on the checks.

The paper's rule (4.3), ``stop.rule = "eps"``, stops on the relative change alone; the
certificate is then evaluated at the stop and reported, and "converged" is true only if it
holds.
"""

import collections
import math

from . import measures

MIN_WINDOW = 1


class Certifier:
    """Tracks W over the run and decides whether the current state is certified (collective:
    every input is a reduced value)."""

    def __init__(self, stop):
        self.stop = stop
        self.w_history = collections.deque()  # (iteration, W^n), every iteration
        self.last = None  # the last full check

    def window(self, iteration):
        return max(MIN_WINDOW, math.ceil(self.stop.w_window * iteration))

    def record(self, iteration, w):
        """W^n of every iteration (free: it comes with the iteration's reduction, which sums
        |X^n|^2 while it makes X^{n+1}: figures of iteration n+1 carry W^n)."""
        self.w_history.append((iteration, w))
        # the window only grows forward: older records than the current target are not needed
        target = iteration - self.window(iteration)
        while len(self.w_history) > 1 and self.w_history[1][0] <= target:
            self.w_history.popleft()

    def w_change(self, iteration, w):
        """|W^n - W^{n-w}| / W^n, W^{n-w} the latest record at least a window old; inf while
        the run is younger than its window."""
        target = iteration - self.window(iteration)
        h = self.w_history
        while len(h) > 1 and h[1][0] <= target:  # targets only grow: older records can go
            h.popleft()
        if not h or h[0][0] > target:
            return math.inf
        old = h[0][1]
        if w == old:  # also W = 0 throughout (one sphere, or nothing to pull together)
            return 0.0
        if not (w > 0):
            return math.inf
        return abs(w - old) / w

    def save(self):
        """The state a restart needs to take the same decisions (JSON-able)."""
        return {"w_history": [[int(i), float(w)] for i, w in self.w_history]}

    def restore(self, saved):
        self.w_history = collections.deque((int(i), float(w)) for i, w in saved["w_history"])

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
        """Every check_every iterations: when the free criteria hold, run the metrics pass.
        Returns True when the state is certified."""
        it = fig["iteration"] - 1  # fig["W"] is W^n, of the positions the step started from
        w_change = self.w_change(it, fig["W"])
        if not (fig["max_overlap"] <= self.stop.overlap and w_change <= self.stop.w_rtol):
            return False
        # all three criteria of one configuration: the current X^{n+1}, its W and its iteration
        # (the certificate at the end of the run is of that same state)
        m, _, _ = measures.measure(solver, overlap_a=False)
        now = fig["iteration"]
        self.last = {"iteration": now, "criteria": self.criteria(
            m["max_overlap"], m["kkt_residual"], self.w_change(now, m["W"]))}
        return all(c["ok"] for c in self.last["criteria"].values())

    def final(self, iteration, final_fig, fired):
        """The certificate of the final state (final_fig from ``measures.finish``). When the
        loop stopped on a certified check (``fired``), that check's verdict is the one
        reported: the final figures are of the same configuration."""
        if fired and self.last is not None and self.last["iteration"] == iteration:
            return self.last["criteria"]
        return self.criteria(final_fig["max_overlap"], final_fig["kkt_residual"],
                             self.w_change(iteration, final_fig["W"]))
