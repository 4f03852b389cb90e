"""The words a run prints about its result (rank 0): the verdict, the certificate, the density.
A number that would mislead is not printed as a result."""


def density_valid(scene, res):
    """A density is a packing's only when the spheres do not overlap beyond the tolerance (the
    covered measure counts an overlap twice) and it is at most 1."""
    return res["max_overlap"] <= scene.stop.overlap and res["density"] <= 1.0


def density_line(scene, res):
    if density_valid(scene, res):
        return (f"packing density {res['density']:.4f} in the ball of radius {res['density_radius']:.3g} "
                f"(radius of gyration) about the centre of mass")
    return (f"packing density not reported: the spheres overlap by up to {res['max_overlap']:.3g} d "
            f"(tolerance {scene.stop.overlap:g}), so the covered measure is not a packing's")


def verdict(scene, res):
    if res["converged"]:
        return "converged (certified)"
    if scene.stop.rule == "eps" and res["stop_reason"] == "eps":
        if not res["certificate"]["overlap"]["ok"]:
            return "stopped by (4.3) on an overlapping configuration, NOT a packing"
        return "stopped by (4.3), NOT certified"
    if scene.stop.rule == "eps" and scene.stop.eps == 0:
        return "ran the requested iterations, not certified"
    return "NOT converged"


def certificate_line(cert):
    names = {"overlap": "max overlap {v:.3e} d", "kkt": "KKT residual {v:.3e}",
             "settled": "W change over the window {v:.3e}"}
    parts = [names[k].format(v=c["value"]) + (" ok" if c["ok"] else f" > {c['tol']:g}")
             + (f" (fitted multipliers; the run's own give {c['run_value']:.3e})"
                if c.get("multipliers") == "fitted" else "")
             for k, c in cert.items()]
    return "certificate: " + ", ".join(parts)


def residual_line(scene, res):
    """Where the run's own KKT residual sits, for a run whose KKT criterion failed: the worst
    sphere's share of the squared residual beside the 1/N of an even spread (a few spheres
    still moving against a whole packing off balance)."""
    where = ("; the snapshots' net_force field shows where" if scene.output.snapshots
             else "; with output.snapshots = true the net_force field shows where")
    return (f"the worst sphere carries {res['net_force_share']:.2%} of the run's squared KKT residual "
            f"(an even spread: 1/N = {1.0 / scene.n:.1e}){where}")
