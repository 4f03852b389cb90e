"""Where is a packing not yet in balance? Reads a run's snapshots.h5 (serially) and reports how
the KKT residual is spread over the spheres: each sphere's net force |g_i| (the snapshot field
net_force, g_i = (X_i - Xbar) + sum_j lambda_ij grad_i phi_ij, the run's multipliers) and, with
--from, how far each sphere moved since an earlier snapshot.

    python tools/net_force_map.py RUN/snapshots.h5 [--iteration I] [--from J] [--png map.png]

Prints the KKT residual sum_i |g_i|^2 / |grad W|^2 rebuilt from the field (the snapshot's own
kkt_residual attribute beside it), how few spheres carry 50%, 90% and 99% of its square, its
share by contact count and by distance from the centre of mass, and with --from the median and
percentiles of the displacements. The picture (2D; in 3D the slab |z - zbar| < d_max) colours
the spheres by log10 net force, and with --from a second panel by log10 displacement: grains of a
2D polycrystal that still slide show as uniform patches with their rotation centres, the
residual along their boundaries (docs/research/convergence.md, section 3i).
"""

import argparse
import math
import sys

import numpy as np


def load(path, iteration):
    from mpipack.io.snapshots import read_snapshot
    fields, attrs = read_snapshot(path, iteration)
    if "net_force" not in fields:
        raise SystemExit(f"net_force_map: {path}: the snapshot has no net_force field (written "
                         "before the field existed: continue the run from a checkpoint to get one)")
    return fields, attrs


def spread(net_force, pull2):
    """(kkt, counts): the residual sqrt(sum |g_i|^2 / sum |X_i - Xbar|^2) and how many spheres,
    largest first, carry 50%, 90% and 99% of its square."""
    sq = np.sort(net_force.astype(float) ** 2)[::-1]
    total = sq.sum()
    kkt = math.sqrt(total / pull2) if pull2 > 0 else math.inf
    if total == 0:
        return kkt, {q: 0 for q in (0.5, 0.9, 0.99)}
    cum = np.cumsum(sq) / total
    return kkt, {q: int(np.searchsorted(cum, q) + 1) for q in (0.5, 0.9, 0.99)}


def report(fields, attrs, before=None):
    """The printed lines (a list of str) and the figures they show (a dict)."""
    x, g = fields["position"], fields["net_force"]
    n = len(g)
    rel = x - x.mean(axis=0)
    r = np.sqrt((rel ** 2).sum(axis=1))
    kkt, counts = spread(g, float((rel ** 2).sum()))
    sq = g.astype(float) ** 2
    share = sq / max(float(sq.sum()), 1e-300)
    lines = [f"iteration {int(attrs['iteration'])}, N = {n}: KKT residual (run's multipliers) {kkt:.4g}"
             f" (snapshot attribute {attrs.get('kkt_residual', float('nan')):.4g})",
             "  spheres carrying " + ", ".join(f"{q:.0%}: {c}" for q, c in counts.items())
             + f" of the squared residual (of {n})"]
    z = fields["contacts"]
    for c in range(int(z.max()) + 1):
        s = z == c
        if s.any():
            lines.append(f"  {c} contacts: {int(s.sum()):8d} spheres, {share[s].sum():6.1%} of it")
    rmax = r.max() if n else 0.0
    for lo, hi in ((0.0, 0.5), (0.5, 0.8), (0.8, 0.95), (0.95, 1.01)):
        s = (r >= lo * rmax) & (r < hi * rmax)
        lines.append(f"  r / r_max {lo:.2f}-{hi:.2f}: {int(s.sum()):8d} spheres, {share[s].sum():6.1%} of it")
    out = {"kkt": kkt, "counts": counts}
    if before is not None:
        moved = np.sqrt(((x - before["position"]) ** 2).sum(axis=1))
        p = np.percentile(moved, [50, 90, 99])
        lines.append(f"  moved since iteration {int(before['iteration'])}: median {p[0]:.3g}, "
                     f"90% {p[1]:.3g}, 99% {p[2]:.3g}, max {moved.max():.3g} (lengths of the scene)")
        out["moved"] = moved
    return lines, out


def draw(path, fields, moved, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    x, g, diam = fields["position"], fields["net_force"], fields["diameter"]
    keep = np.ones(len(g), bool)
    if x.shape[1] == 3:  # a slab through the centre of mass
        keep = np.abs(x[:, 2] - x[:, 2].mean()) < diam.max()
    if x.shape[1] == 1:
        x = np.column_stack([x[:, 0], np.zeros(len(x))])
    panels = [("log10 net force |g_i|", np.log10(g + 1e-300), "magma")]
    if moved is not None:
        panels.insert(0, ("log10 displacement", np.log10(moved + 1e-12), "viridis"))
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 7), squeeze=False)
    for ax, (name, value, cmap) in zip(axes[0], panels):
        order = np.argsort(value[keep])
        xs = x[keep][order]
        lo, hi = np.percentile(value[keep], [5, 99.9]) if keep.any() else (0, 1)
        sc = ax.scatter(xs[:, 0], xs[:, 1], c=value[keep][order], s=max(0.02, 2e4 / max(keep.sum(), 1)),
                        cmap=cmap, vmin=lo, vmax=hi, rasterized=True)
        fig.colorbar(sc, ax=ax, shrink=0.8)
        ax.set_title(f"{title}: {name}")
        ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(path, dpi=60)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("snapshots", help="a run's snapshots.h5")
    p.add_argument("--iteration", type=int, default=None, help="the snapshot (default: the last)")
    p.add_argument("--from", dest="before", type=int, default=None,
                   help="an earlier snapshot's iteration: also report displacements since then")
    p.add_argument("--png", default=None, help="draw the map into this PNG")
    a = p.parse_args(argv)
    fields, attrs = load(a.snapshots, a.iteration)
    before = None
    if a.before is not None:
        from mpipack.io.snapshots import read_snapshot
        bf, ba = read_snapshot(a.snapshots, a.before)
        before = {"position": bf["position"], "iteration": ba["iteration"]}
    lines, out = report(fields, attrs, before)
    print("\n".join(lines))
    if a.png:
        draw(a.png, fields, out.get("moved"), f"iteration {int(attrs['iteration'])}")
        print(f"map: {a.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
