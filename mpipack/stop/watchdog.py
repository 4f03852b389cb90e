"""Numerical trouble found during a run, within a bounded number of iterations: divergence
(the cloud blown out, W, the multipliers or the overlap growing) and oscillation without
progress (AHA-S's periodic orbit of the paper's Fig. 2, an unstable contact that keeps ringing).

The watchdog reads only reduced figures (the same on every rank), so its verdicts are
collective, and it changes nothing in the state: a run it does not stop is bitwise the run
without it. The iterations are cut into blocks of ``BLOCK``; per block it keeps

    r_mean  mean over the block of the relative change ||X^{n+1} - X^n|| / ||X^n||  (4.3)
    o_min, o_mean   min and mean over the block of the max overlap (d_kl - |X_k - X_l|) / d_kl
    w_min, w_max   the range of W over the block
    lam     max lambda_kl at the block's end (one allreduce per block)
    settled |W^n - W^{n-w}| / W^n at the block's end (the certificate's window)
    kkt     the certificate's KKT residual, when a certified check ran in the block

and at each block's end decides:

    blown out   the radius of gyration sqrt(2 w_min / N) exceeds BLOWOUT x the natural size
                (the start's radius of gyration or d N^(1/b), whichever is larger): no
                packing is that large;
    growing     W (above GROW_ABOVE x its natural value ½ N r_natural^2), max lambda (above
                GROW_ABOVE x the virial mean multiplier of ``schedule.packing_law``) or the
                block's smallest max overlap (above GROW_ABOVE x stop.overlap and GROW_ABOVE x
                the run's best) rose by at least x GROWTH in each of the last GROW_BLOCKS
                blocks: exponential growth, an unstable iteration. Multipliers and overlaps
                also grow, for a while, in a cloud falling together (from 3e-4 to 4e-2 d over
                750 iterations in a 2D N = 1e5 fire-al run, W falling by ~1% per block); they
                count only once W has settled (the certificate's ``settled`` figure, its change
                over the last tenth of the run, at most SETTLED = 1e-3);
    no progress over the last window of blocks (STALL_BLOCKS x BLOCK = 3000 iterations, or
                half the run's age, up to MAX_STALL_BLOCKS x BLOCK = 12000), split into an
                older and a newer half: in none of r_mean, o_mean, w_max, w_max - w_min,
                settled, kkt (lower is better) and w_min (higher: an expanding cloud) is the
                median of the newer half's blocks better than the older half's by PROGRESS
                (10%). A cycle whose period fits in a half repeats the same figures in both
                halves; a wander does not improve their medians; a converging run does (a
                linearly convergent iteration lowers r_mean, a falling cloud W, a damped
                breathing the range of W, a settling one ``settled``) unless it gains less than
                10% in a window. The halves slide with the run, so a phase whose figures were
                better in another way long ago (no contacts yet: overlap 0) sets no bar for
                later ones; the window grows with the run's age because slow transients grow
                with it (a spread start of 200 spheres under the suite's fixed parameters
                collapses, bounces back and collapses again with a period of about 6000
                iterations before it certifies at 26900).

Each verdict is a message that names what happened and a parameter change that would help;
the loop raises it as ``solver.NumericalError`` (exit 3, the last state checkpointed).
``stop.watchdog = false`` turns it off; the no-progress test is also off when the run asked
for a fixed number of iterations (stop.rule = "eps", stop.eps = 0).
"""

import copy
import math
import statistics

BLOCK = 250
STALL_BLOCKS = 12     # the no-progress window: 3000 iterations, or half the run's age ...
MAX_STALL_BLOCKS = 48  # ... up to 12000 iterations
PROGRESS = 0.9        # an improvement is one by at least 10%
GROWTH = 2.0          # growth by x2 per block ...
GROW_BLOCKS = 3       # ... in each of 3 consecutive blocks
GROW_ABOVE = 10.0     # only above 10 x the figure's natural scale
BLOWOUT = 100.0       # radius of gyration beyond 100 x the natural size
SETTLED = 1e-3        # multipliers and overlap count as growing only in a settled cloud

# the figures of the no-progress test: lower is better, except w_min (an expanding cloud)
_LOWER = ("r_mean", "o_mean", "w_max", "w_range", "settled", "kkt")
_HISTORY = max(MAX_STALL_BLOCKS, GROW_BLOCKS + 1)


class Watchdog:
    """Per-run state of the checks. ``observe(fig)`` every iteration with the reduced figures;
    at a block's end ``block_end(iteration, lam_max, settled, kkt)`` returns None or
    (kind, message)."""

    def __init__(self, n, r_natural, lam_bar, overlap_tol, stall=True, advice=""):
        self.n = n
        self.r_natural = r_natural
        self.w_natural = 0.5 * n * r_natural * r_natural
        self.lam_bar = lam_bar
        self.overlap_tol = overlap_tol
        self.stall = stall
        self.advice = advice
        self.s = {"block": self._empty(), "history": [], "best_overlap": math.inf}

    @staticmethod
    def _empty():
        return {"r_sum": 0.0, "o_sum": 0.0, "count": 0, "o_min": math.inf, "w_min": math.inf,
                "w_max": -math.inf}

    def observe(self, fig):
        b = self.s["block"]
        r, o, w = fig["relative_change"], fig["max_overlap"], fig["W"]
        b["r_sum"] += r
        b["o_sum"] += o
        b["count"] += 1
        if o < b["o_min"]:
            b["o_min"] = o
        if w < b["w_min"]:
            b["w_min"] = w
        if w > b["w_max"]:
            b["w_max"] = w

    def due(self, iteration):
        return iteration % BLOCK == 0

    def block_end(self, iteration, lam_max, settled, kkt=math.nan):
        """Close the block ending at ``iteration``; a verdict (kind, message) or None."""
        s = self.s
        b = dict(s["block"], lam=lam_max, settled=settled, kkt=kkt, iteration=iteration)
        b["w_range"] = b["w_max"] - b["w_min"]
        count = max(b.pop("count"), 1)
        b["r_mean"], b["o_mean"] = b.pop("r_sum") / count, b.pop("o_sum") / count
        s["block"] = self._empty()
        s["history"] = (s["history"] + [b])[-_HISTORY:]
        s["best_overlap"] = min(s["best_overlap"], b["o_min"])
        verdict = self._blown_out(b) or self._growing()
        if verdict:
            return verdict
        window = self.window(iteration)
        if self.stall and len(s["history"]) >= window and not self._progress(window):
            return "stalled", (
                f"no progress toward a packing (a cycle or a wander): over the {window * BLOCK} "
                f"iterations up to {iteration} none of the max overlap (mean {b['o_mean']:.3g} d), "
                f"the relative change (mean {b['r_mean']:.3g}), W (between {b['w_min']:.6g} and "
                f"{b['w_max']:.6g}) and its settling improved by {1 - PROGRESS:.0%}; {self.advice}")
        return None

    def _blown_out(self, b):
        r_gyr = math.sqrt(2.0 * max(b["w_min"], 0.0) / self.n)
        if r_gyr > BLOWOUT * self.r_natural:
            return "diverged", (
                f"the cloud has blown out: radius of gyration {r_gyr:.3g} at iteration {b['iteration']}, "
                f"{r_gyr / self.r_natural:.3g} times its natural size {self.r_natural:.3g}; {self.advice}")
        return None

    def _growing(self):
        h = self.s["history"][-(GROW_BLOCKS + 1):]
        if len(h) < GROW_BLOCKS + 1:
            return None
        checks = [("W", "w_max", GROW_ABOVE * self.w_natural)]
        if h[-1]["settled"] <= SETTLED:
            checks += [("the largest multiplier", "lam", GROW_ABOVE * self.lam_bar),
                       ("the max overlap", "o_min", GROW_ABOVE * max(self.overlap_tol, self.s["best_overlap"]))]
        for what, key, floor in checks:
            values = [blk[key] for blk in h]
            if not all(math.isfinite(v) for v in values):
                continue
            if values[-1] > floor and all(b > GROWTH * a > 0 for a, b in zip(values, values[1:])):
                return "diverged", (
                    f"divergence: {what} grew from {values[0]:.3g} to {values[-1]:.3g} between "
                    f"iterations {h[0]['iteration']} and {h[-1]['iteration']} (at least x{GROWTH:g} "
                    f"every {BLOCK} iterations); {self.advice}")
        return None

    @staticmethod
    def window(iteration):
        """Blocks in the no-progress window at ``iteration`` (even)."""
        half_age = (iteration // BLOCK) // 4 * 2
        return min(MAX_STALL_BLOCKS, max(STALL_BLOCKS, half_age))

    def _progress(self, window):
        """Whether the newer half of the last ``window`` blocks beats the older half by
        PROGRESS in any figure, half against half by the median of the blocks' values (a
        chaotic orbit throws up a lucky block now and then; its medians stay put)."""
        h = self.s["history"][-window:]
        older, newer = h[:window // 2], h[window // 2:]

        def typical(blocks, key):
            values = [blk[key] for blk in blocks if math.isfinite(blk[key])]
            return statistics.median(values) if values else None

        for key in _LOWER:
            a, b = typical(older, key), typical(newer, key)
            if a is not None and b is not None and b < PROGRESS * a:
                return True
        a, b = typical(older, "w_min"), typical(newer, "w_min")
        return a is not None and b is not None and PROGRESS * b > a

    def save(self):
        """The state a restart needs to take the same decisions (JSON-able; the checkpoint's
        JSON keeps infinities)."""
        return copy.deepcopy(self.s)

    def restore(self, saved):
        self.s = copy.deepcopy(saved)
