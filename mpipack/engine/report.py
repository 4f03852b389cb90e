"""The words a run prints about its result (rank 0): the verdict, the certificate, the density.
A number that would mislead is not printed as a result."""


def density_slack(scene, res):
    """How far above 1 the covered measure of a packing may come from overlaps within the
    tolerance, which it counts twice: at most 2 b times the largest relative overlap (a 1D chain
    certified at overlaps of 3e-6 d covers 1.000002 of its interval)."""
    return 2.0 * scene.dim * res["max_overlap"]


def density_valid(scene, res):
    """A density is a packing's only when the spheres do not overlap beyond the tolerance and
    the covered measure is at most 1 up to what those overlaps add (``density_slack``). In a
    container the ball about the centre of mass crosses the walls: no density of that ball."""
    if scene.container.active:
        return False
    return res["max_overlap"] <= scene.stop.overlap and res["density"] <= 1.0 + density_slack(scene, res)


def reported_density(scene, res):
    """The density a packing reports: the covered fraction, 1 where overlaps within the
    tolerance took it above 1; None for a configuration that is not a packing."""
    return min(res["density"], 1.0) if density_valid(scene, res) else None


def density_line(scene, res):
    if scene.container.active:
        return (f"packing density not reported about the centre of mass (its ball crosses the "
                f"container's walls): `mpipack post density` gives the fraction inside the container")
    if density_valid(scene, res):
        where = (f"in the ball of radius {res['density_radius']:.3g} (radius of gyration) about the "
                 f"centre of mass")
        if res["density"] > 1.0:
            return (f"packing density 1 to within the overlap tolerance {where} (the covered measure, "
                    f"{res['density']:.7g}, counts each overlap twice)")
        return f"packing density {res['density']:.4f} {where}"
    return (f"packing density not reported: the spheres overlap by up to {res['max_overlap']:.3g} d "
            f"(tolerance {scene.stop.overlap:g}), so the covered measure is not a packing's")


def verdict(scene, res):
    if res["converged"]:
        return "converged (certified)"
    if scene.stop.rule == "jammed" and res["stop_reason"] == "jammed":
        # the figures on the verdict's own line: --quiet prints it alone
        return (f"jammed (not certified): max overlap {res['max_overlap']:.3e} d, KKT residual "
                f"{res['kkt_residual']:.3e} (not required), W = {res['W']:.10g}")
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
