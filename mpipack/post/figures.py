"""The pictures of ``mpipack post`` (matplotlib, headless; rank 0 only). A measure's warnings
are printed in red across the top of its figure, so a figure that looks wrong says so."""

import math

import numpy as np


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _flag(fig, warnings):
    if warnings:
        fig.suptitle("WARNING: " + "; ".join(warnings), color="red", fontsize=8, wrap=True)


def _save(fig, path):
    fig.savefig(path, dpi=120)
    _plt().close(fig)
    return path


def density(path, m, label=""):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    p, s = m.picture, m.summary
    ax.plot(p["R"] / p["d"], p["phi"], label=label or "phi(R)")
    if math.isfinite(s["plateau"]):
        ax.axhline(s["plateau"], color="grey", ls=":", label=f"plateau {s['plateau']:.4f}")
        if math.isfinite(s["plateau_from"]):
            ax.axvspan(s["plateau_from"] / p["d"], s["plateau_to"] / p["d"], color="grey", alpha=0.15)
    ax.axhline(s["densest"], color="black", lw=0.6, ls="--", label=f"densest {s['densest']:.4f}")
    ax.set_xlabel("R / d (about the centre of mass)")
    ax.set_ylabel("covered fraction phi(R)")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    _flag(fig, m.warnings)
    fig.tight_layout()
    return _save(fig, path)


def profile(path, p, warnings=()):
    """A container's profile: p["y"] against p["x"], and p["bars"] (the centres' histogram)
    on a second axis when given."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    x = np.asarray(p["x"])
    if p.get("bars") is not None:
        twin = ax.twinx()
        width = x[1] - x[0] if len(x) > 1 else 1.0
        twin.bar(x, np.asarray(p["bars"]), width=width, color="grey", alpha=0.3)
        twin.set_ylabel("centres (grey)")
    ax.plot(x, np.asarray(p["y"]), marker=".", zorder=3)
    ax.set_xlabel(p["xlabel"])
    ax.set_ylabel(p["ylabel"])
    ax.set_ylim(0, 1.05)
    _flag(fig, list(warnings))
    fig.tight_layout()
    return _save(fig, path)


def histogram(path, m, x, y, xlabel, ylabel="share of spheres", scale=1.0):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.bar(np.asarray(m.table[x]), np.asarray(m.table[y]) * scale, width=0.8 if x in ("neighbours", "contacts") else
           (np.asarray(m.table[x])[1] - np.asarray(m.table[x])[0] if len(m.table[x]) > 1 else 1.0), align="edge"
           if x not in ("neighbours", "contacts") else "center")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    _flag(fig, m.warnings)
    fig.tight_layout()
    return _save(fig, path)


def curve(path, x, y, xlabel, ylabel, warnings=(), hline=None):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(x, y)
    if hline is not None:
        ax.axhline(hline, color="grey", ls=":")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    _flag(fig, list(warnings))
    fig.tight_layout()
    return _save(fig, path)


def spheres(path, rows, values, label, warnings=(), cmap="viridis", chains=None, dim=2):
    """Discs to scale coloured by ``values`` (2D; in 3D the cross-sections of the slab through
    the centre, radius sqrt(r^2 - dz^2)); values None: pale discs. With ``chains`` {"gi", "gj",
    "lam"}, the contacts as lines of width and colour following lambda (the force chains)."""
    from matplotlib.collections import LineCollection, PatchCollection
    from matplotlib.patches import Circle
    plt = _plt()
    x = rows["x"]
    r = 0.5 * rows["diam"]
    if dim == 3:
        dz = x[:, 2] - np.median(x[:, 2]) if len(x) else np.zeros(0)
        r = np.sqrt(np.maximum(r * r - dz * dz, 0.0))
    xy = x[:, :2] if x.shape[1] >= 2 else np.column_stack([x[:, 0], np.zeros(len(x))])
    fig, ax = plt.subplots(figsize=(7, 6.5))
    discs = [Circle(p, s) for p, s in zip(xy, r)]
    if values is None:  # the force chains over pale discs
        ax.add_collection(PatchCollection(discs, facecolor="0.92", edgecolor="0.75", linewidths=0.3))
    else:
        coll = PatchCollection(discs, cmap=cmap, linewidths=0)
        coll.set_array(np.asarray(values))
        ax.add_collection(coll)
        fig.colorbar(coll, ax=ax, label=label)
    if chains is not None and len(chains["gi"]):
        order = np.argsort(rows["gid"])
        a = order[np.searchsorted(rows["gid"], chains["gi"], sorter=order)]
        b = order[np.searchsorted(rows["gid"], chains["gj"], sorter=order)]
        lam = np.asarray(chains["lam"])
        width = 3.0 * lam / lam.max() if lam.max() > 0 else np.ones(len(lam))
        lines = LineCollection(np.stack([xy[a], xy[b]], axis=1), linewidths=width, cmap="inferno_r")
        lines.set_array(lam)
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, label="lambda_ij (contact force)")
    if len(xy):
        pad = float(r.max()) if len(r) else 1.0
        ax.set_xlim(xy[:, 0].min() - pad, xy[:, 0].max() + pad)
        ax.set_ylim(xy[:, 1].min() - pad, xy[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.set_title(f"{len(xy)} spheres" + (" (slab through the centre)" if dim == 3 else ""), fontsize=9)
    _flag(fig, list(warnings))
    fig.tight_layout()
    return _save(fig, path)


def convergence(path, columns, warnings=()):
    """Relative change, max overlap, W and KKT residual against iteration and wall time."""
    plt = _plt()
    names = [k for k in ("relative_change", "max_overlap", "W", "kkt_residual") if k in columns]
    fig, axes = plt.subplots(len(names), 2, figsize=(9, 2.3 * len(names)), squeeze=False)
    for row, name in enumerate(names):
        for col, xname in enumerate(("iteration", "wall_seconds")):
            ax = axes[row][col]
            y = np.asarray(columns[name], dtype=float)
            x = np.asarray(columns[xname], dtype=float)
            ok = np.isfinite(y) & (y > 0)
            ax.semilogy(x[ok], y[ok])
            ax.set_xlabel(xname.replace("_", " "))
            ax.set_ylabel(name.replace("_", " "))
    _flag(fig, list(warnings))
    fig.tight_layout()
    return _save(fig, path)


def overlay(path, curves, xlabel, ylabel, warnings=()):
    """Several runs' curves [(label, x, y)] on one axis."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, x, y in curves:
        ax.plot(x, y, label=label, lw=1)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if len(curves) <= 12:
        ax.legend(fontsize=7)
    _flag(fig, list(warnings))
    fig.tight_layout()
    return _save(fig, path)
