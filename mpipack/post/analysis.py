"""One packing's measures on MPI ranks: read, spread by space with a halo, measure, reduce.

    a = Analysis(comm, packing, reach)       # packing: source.read(...); reach: the halo width
    a.density(), a.neighbours(t), a.contacts(gap), a.pressure(), a.gr(r_max, bins), a.order(t)

Each returns a ``Measure``: ``summary`` (numbers, the same on every rank and rank count),
``table`` (the columns of its CSV), ``picture`` (what its figure draws, on rank 0 only) and
``warnings`` (what makes a number suspect: said next to it, never silently printed).
"""

import dataclasses
import math

import numpy as np

from . import container as box, halo, measures, source

PICTURE_MAX = 200_000     # spheres drawn in one picture at most (a window about the centre)
FIRST_PEAK_WINDOW = 1.5   # g(r)'s first peak: its maximum over r <= 1.5 mean diameters


def centres_first_layer(mid, centres, first):
    """Where the centres' first layer lies, in units of d: the heaviest pair of adjacent bins
    among those whose middle ``mid`` (sorted, (k,)) is flagged ``first`` (the first 1.5 d), at
    its count-weighted mean. A pair, not one bin: the spheres touching a wall sit at t = d/2,
    a bin edge, and split about evenly between two bins, either of which a second layer that
    falls in one bin may outweigh. centres (k,) counts; 0.0 if there are none."""
    c = np.asarray(centres, dtype=np.float64)
    pair = c[:-1] + c[1:]
    ok = first[:-1] & (pair > 0)
    if not ok.any():
        return 0.0
    q = int(np.argmax(np.where(ok, pair, -1.0)))
    return float((mid[q] * c[q] + mid[q + 1] * c[q + 1]) / pair[q])


@dataclasses.dataclass
class Measure:
    name: str
    summary: dict
    table: dict
    picture: object = None
    warnings: list = dataclasses.field(default_factory=list)
    parts: dict = dataclasses.field(default_factory=dict)  # more figures: {suffix: (table, picture)}


class Analysis:
    """The packing spread over the ranks by space, its centre and size (module docstring)."""

    def __init__(self, comm, packing, reach):
        self.comm, self.packing = comm, packing
        self.n, self.dim = packing.n, packing.dim
        fields = dict(packing.fields)
        self.d_max = float(comm.allreduce(np.array([packing.diam.max() if len(packing.diam) else 0.0]), "max")[0])
        self.d_mean = halo.exact_total(comm, packing.diam) / self.n
        self.reach = max(float(reach), 1.1 * self.d_max)
        self.local = halo.distribute(comm, packing.gid, packing.x, packing.diam, self.reach, fields)
        self.xbar = measures.centre_of_mass(comm, self.local, self.n)
        self.r_gyr = measures.gyration_radius(comm, self.local, self.xbar, self.n)
        self.r_cluster = measures.cluster_radius(self.dim, self.r_gyr)
        self.r_max = float(comm.allreduce(np.array([np.sqrt(((self.local.x[:self.local.n_own] - self.xbar) ** 2)
                                                            .sum(axis=1)).max() if self.local.n_own else 0.0]), "max")[0])
        self._plateau = None
        self._contacts = {}
        self._pairs = {}
        self._contact_pairs = None
        self.container = box.of_scene(packing.scene, self.dim)

    # ---- shared pieces -----------------------------------------------------------------------
    def pairs(self, factor):
        if factor not in self._pairs:
            self._pairs[factor] = measures.close_pairs(self.local, factor, self.d_max)
        return self._pairs[factor]

    def quality_warnings(self):
        """What says this packing is not (yet) a packing: overlaps beyond the run's tolerance,
        a run that did not converge, a snapshot before the end."""
        out = []
        pk = self.packing
        tol = (pk.scene.get("stop") or {}).get("overlap", 1e-3) if isinstance(pk.scene, dict) else 1e-3
        overlap = pk.attrs.get("max_overlap")
        if overlap is not None and isinstance(overlap, (int, float)) and math.isfinite(overlap) and overlap > tol:
            out.append(f"max overlap {overlap:.3g} d > the run's tolerance {tol:.3g} d: not a packing yet")
        s = pk.summary
        if s and int(s.get("iterations", -1)) == pk.iteration and s.get("converged") is False:
            out.append(f"the run did not converge ({s.get('exit_status', s.get('stop_reason', 'not certified'))})")
        elif s and int(s.get("iterations", -1)) > pk.iteration:
            out.append(f"snapshot of iteration {pk.iteration}, before the run's end ({s.get('iterations')})")
        return out

    def plateau(self):
        if self._plateau is None:
            radii = self.radii()
            phi = measures.density_profile(self.comm, self.local, self.xbar, radii)
            self._plateau = (radii, phi, measures.plateau(radii, phi, self.d_mean, self.r_cluster))
        return self._plateau

    def radii(self, count=200):
        top = self.r_max + 0.5 * self.d_max
        return np.linspace(top / count, top, count)

    def _window(self):
        """The rows of this rank a picture draws: in 2D the discs nearest the centre (all when
        N <= PICTURE_MAX), in 3D the slab |x_3 - Xbar_3| < d/2 through the centre."""
        own = self.local.x[:self.local.n_own]
        if self.dim == 3:
            keep = np.abs(own[:, 2] - self.xbar[2]) < 0.5 * self.d_mean
        else:
            keep = np.ones(len(own), dtype=bool)
        count = int(halo.total(self.comm, np.array([keep.sum()]))[0])
        if count > PICTURE_MAX:
            dist = np.sqrt(((own[:, :2] - self.xbar[:2]) ** 2).sum(axis=1))
            keep &= dist <= self.r_max * math.sqrt(PICTURE_MAX / count)
        return keep

    def picture_rows(self, values=None):
        """On rank 0: {"gid", "x", "diam", ...values} of the window (gid order), None elsewhere."""
        keep = self._window()
        arrays = {"gid": self.local.gid[:self.local.n_own][keep], "x": self.local.x[:self.local.n_own][keep],
                  "diam": self.local.diam[:self.local.n_own][keep]}
        arrays.update({k: np.asarray(v)[keep] for k, v in (values or {}).items()})
        got = halo.gather_rows(self.comm, arrays)
        if got is not None:
            order = np.argsort(got["gid"], kind="stable")
            got = {k: v[order] for k, v in got.items()}
        return got

    # ---- the measures ------------------------------------------------------------------------
    def density(self):
        radii, phi, (value, r_from, r_to) = self.plateau()
        at_gyr = float(measures.density_profile(self.comm, self.local, self.xbar, np.array([self.r_gyr]))[0])
        top = measures.MAX_DENSITY[self.dim]
        warn = self.quality_warnings()
        if not math.isfinite(value):
            warn.append("no plateau: the cluster is too small (fewer than 3 radii between 2 d and 0.7 R_c)")
        elif value > top * (1 + 1e-9):
            warn.append(f"plateau density {value:.4f} above the densest packing's {top:.4f}: the spheres overlap")
        summary = {"plateau": value, "plateau_from": r_from, "plateau_to": r_to,
                   "plateau_tolerance": measures.PLATEAU_TOLERANCE, "density_at_gyration_radius": at_gyr,
                   "gyration_radius": self.r_gyr, "cluster_radius": self.r_cluster, "densest": top,
                   "centre_of_mass": [float(v) for v in self.xbar]}
        parts = {}
        if self.container is not None:
            summary["container"], parts = self.in_container(warn)
        return Measure("density", summary, {"R": radii, "R_over_d": radii / self.d_mean, "phi": phi},
                       picture={"R": radii, "phi": phi, "d": self.d_mean}, warnings=warn, parts=parts)

    def in_container(self, warn):
        """The packing fraction inside the container, its profiles along the axis and from
        the wall (``container``): (summary, {suffix: (table, picture)}); adds to ``warn``."""
        c, dim, d = self.container, self.dim, self.d_mean
        n = self.local.n_own
        x, diam = self.local.x[:n], self.local.diam[:n]
        vol, side, doubtful = box.inside_volumes(c, dim, x, diam)
        inside, cut_side = halo.exact_totals(self.comm, [vol, side])
        doubtful = int(halo.total(self.comm, np.array([doubtful]))[0])
        top = None
        if c.kind == "cylinder" and c.height is None:  # open: up to the highest sphere's top
            top = float(self.comm.allreduce(np.array([(x[:, 2] + 0.5 * diam).max() if n else -np.inf]), "max")[0])
        volume = box.measure(c, dim, top)
        phi = inside / volume
        summary = {"kind": c.kind, "walls": c.names, "volume": volume, "covered": inside,
                   "packing_fraction": phi, "side_walls_cut": cut_side}
        if top is not None:
            summary["open_top"] = top
            warn.append(f"open cylinder: its volume is taken up to the highest sphere's top, z = {top:.4g}")
        if doubtful:
            warn.append(f"{doubtful} sphere-wall pairs stick out so far (more than 0.29 r) that two walls' cuts "
                        "may overlap: their volume inside is approximate")
        if phi > measures.MAX_DENSITY[dim] * (1 + 1e-9):
            warn.append(f"packing fraction {phi:.4f} in the container above the densest packing's "
                        f"{measures.MAX_DENSITY[dim]:.4f}: the spheres overlap")
        parts = {}
        clip = None  # the nearest-wall profile's region: below the bed's top when the spheres fill part of it
        span = box.axis_range(c, dim, top)
        if span is not None:
            z0, z1 = span
            k = max(int(math.ceil((z1 - z0) / d - 1e-9)), 1)
            edges = np.minimum(z0 + d * np.arange(k + 1), z1)
            edges[-1] = z1
            covered = box.axis_profile(self.comm, c, dim, x, diam, vol, side, edges)
            slab = box.cross_section(c, dim) * np.diff(edges)
            prof = covered / slab
            parts["axis"] = ({"from": edges[:-1], "to": edges[1:], "middle_over_d": 0.5 * (edges[1:] + edges[:-1] - 2 * z0) / d,
                              "covered": covered, "slab": slab, "phi": prof},
                             {"x": 0.5 * (edges[1:] + edges[:-1] - 2 * z0) / d, "y": prof,
                              "xlabel": f"height above the floor / d ({'yz'[dim - 2]})",
                              "ylabel": "covered fraction of the slab"})
            summary["axis_profile"] = {"axis": "yz"[dim - 2], "slab_height": d, "slabs": k, "floor": z0, "top": z1,
                                       "phi_min": float(prof.min()), "phi_max": float(prof.max())}
            # the bed: the slabs from 2 d above the floor to 2 d below the spheres' free surface
            # (a container filled to part of its height counts the empty room above in phi)
            surface = float(self.comm.allreduce(
                np.array([(x[:, dim - 1] + 0.5 * diam).max() if n else -np.inf]), "max")[0])
            bed = (edges[:-1] >= z0 + 2 * d) & (edges[1:] <= surface - 2 * d)
            if surface < z1 - 2 * d or (c.kind == "cylinder" and c.height is None):
                clip = surface - 2 * d
            if bed.any():
                phi_bed = float(covered[bed].sum() / slab[bed].sum())
                summary["bed"] = {"from": float(edges[:-1][bed][0]), "to": float(edges[1:][bed][-1]),
                                  "surface": surface, "packing_fraction": phi_bed}
                if surface < z1 - 2 * d:
                    warn.append(f"the spheres fill the container up to {surface:.4g} of {z1:.4g}: its packing "
                                f"fraction counts the empty room above; the bed's (slabs {2:d} d from the floor "
                                f"and the surface) is {phi_bed:.4f}")
        edges = np.arange(box.WALL_RANGE_D * box.WALL_BINS_PER_D + 1) * (d / box.WALL_BINS_PER_D)
        mid = 0.5 * (edges[1:] + edges[:-1]) / d
        first = mid <= 1.5

        def peaks(covered, shell, centres):
            with np.errstate(divide="ignore", invalid="ignore"):
                prof = np.where(shell > 0, covered / np.where(shell > 0, shell, 1.0), np.nan)
            q = int(np.nanargmax(np.where(first & np.isfinite(prof), prof, -np.inf)))
            return prof, {"first_peak_t_over_d": float(mid[q]), "first_peak_phi": float(prof[q]),
                          "centres_first_peak_t_over_d": centres_first_layer(mid, centres, first),
                          "centres_within_range": int(centres.sum())}

        # the headline: from the nearest wall (C_t the container shrunk by t, clipped at the bed's top)
        covered, shell, centres = box.nearest_wall_profile(self.comm, c, dim, x, diam, edges, clip)
        prof, found = peaks(covered, shell, centres)
        summary["wall_profile"] = {"distance": "to the nearest wall", "bin_over_d": 1.0 / box.WALL_BINS_PER_D,
                                   "range_over_d": box.WALL_RANGE_D, "clip_height": clip,
                                   "region": ("the container" if clip is None else
                                              "the container below clip_height (2 d under the spheres' free "
                                              "surface, which is no wall)"),
                                   **found, "covered": float(covered.sum()), "shells": float(shell.sum())}
        parts["wall"] = ({"t_from": edges[:-1], "t_to": edges[1:], "t_over_d": mid, "covered": covered,
                          "shell": shell, "phi": prof, "centres": centres},
                         {"x": mid, "y": prof, "xlabel": "distance from the nearest wall / d",
                          "ylabel": "covered fraction", "bars": centres})
        # each wall's own distance, pooled over the walls
        covered, shell, centres = box.wall_profile(self.comm, c, dim, x, diam, edges, top)
        prof, found = peaks(covered, shell, centres)
        summary["wall_profile_pooled"] = {"bin_over_d": 1.0 / box.WALL_BINS_PER_D, "range_over_d": box.WALL_RANGE_D,
                                          "pooled": "each wall's slabs (shells) of its own distance, summed over the walls",
                                          **found}
        parts["wall-pooled"] = ({"t_from": edges[:-1], "t_to": edges[1:], "t_over_d": mid, "covered": covered,
                                 "shell": shell, "phi": prof, "centres": centres},
                                {"x": mid, "y": prof, "xlabel": "distance from each wall / d",
                                 "ylabel": "covered fraction (pooled over the walls)", "bars": centres})
        return summary, parts

    def without_rattlers(self, gap=1e-3):
        """The owned spheres that are not rattlers (mask), of the multiplier network when the
        file holds the pairs, else of the gap network; and the global count."""
        _, rattler_gids = self.contacts(gap)
        alive = ~np.isin(self.local.gid[:self.local.n_own], rattler_gids)
        return alive, int(halo.total(self.comm, np.array([alive.sum()]))[0])

    def _kept_pairs(self, factor, exclude_rattlers, gap):
        """(i, j, mask of the owned spheres counted, how many over all ranks)."""
        i, j, _ = self.pairs(factor)
        if not exclude_rattlers:
            return i, j, np.ones(self.local.n_own, dtype=bool), self.n
        alive, count = self.without_rattlers(gap)
        alive_all = self.local.with_halo(alive.astype(np.int8)).astype(bool)
        keep = alive_all[i] & alive_all[j]
        return i[keep], j[keep], alive, count

    def neighbours(self, factor=1.1, exclude_rattlers=False, gap=1e-3):
        i, _, alive, n_counted = self._kept_pairs(factor, exclude_rattlers, gap)
        count = np.bincount(i, minlength=self.local.n_own)[:self.local.n_own][alive]
        hist = measures.count_histogram(self.comm, count)
        k = np.arange(len(hist))
        mean = float(np.dot(k, hist)) / n_counted if n_counted else math.nan
        summary = {"factor": factor, "mean": mean, "max": int(k[hist > 0].max()) if hist.any() else 0,
                   "spheres": n_counted, "rattlers_excluded": bool(exclude_rattlers)}
        if self.dim == 3:
            summary["share_8_to_10"] = float(hist[8:11].sum()) / n_counted if n_counted else math.nan
        if self.dim == 2:
            summary["share_6"] = float(hist[6]) / n_counted if len(hist) > 6 and n_counted else 0.0
        kissing = {1: 2, 2: 6, 3: 12}[self.dim]
        warn = self.quality_warnings()
        if factor <= 1.0 + 1e-12 and summary["max"] > kissing:
            warn.append(f"a sphere has {summary['max']} touching neighbours, more than the kissing number {kissing}")
        return Measure("neighbours", summary, {"neighbours": k, "spheres": hist,
                                               "share": hist / n_counted if n_counted else hist * 0.0},
                       picture={"k": k, "hist": hist}, warnings=warn)

    def contacts(self, gap=1e-3):
        """The network of pairs with lambda > 0 (when the file holds the pairs; else the
        per-sphere counts of the snapshot) and the network of pairs with gap < ``gap`` d_ij.
        Returns (Measure, gids of the rattlers of the multiplier network when there is one, else
        of the gap network); computed once per gap (``without_rattlers`` asks for it too)."""
        if gap not in self._contacts:
            self._contacts[gap] = self._measure_contacts(gap)
        return self._contacts[gap]

    def _measure_contacts(self, gap):
        i, j, _ = self.pairs(1.0 + gap)
        by_gap, alive = measures.contact_summary(self.comm, self.local, i, j, self.dim, self.n)
        summary = {"gap": gap, "by_gap": {k: v for k, v in by_gap.items() if k != "histogram"}}
        table = {"contacts": np.arange(len(by_gap["histogram"])), "spheres_by_gap": by_gap["histogram"]}
        warn = self.quality_warnings()
        pk = self.packing
        if pk.pairs is not None:
            try:
                mi, mj, lam = halo.route_pairs(self.comm, self.local, int(pk.gid[0]) if len(pk.gid) else 0, *pk.pairs)
            except ValueError as e:
                raise source.PostError(f"{pk.path}: snapshot {pk.iteration}: {e}") from None
            by_lam, alive_lam = measures.contact_summary(self.comm, self.local, mi, mj, self.dim, self.n)
            summary["by_multiplier"] = {**{k: v for k, v in by_lam.items() if k != "histogram"},
                                        "source": "the snapshot's contact pairs (lambda_ij > 0)"}
            m = max(len(by_lam["histogram"]), len(table["contacts"]))
            table = {"contacts": np.arange(m), "spheres_by_gap": _pad(by_gap["histogram"], m),
                     "spheres_by_multiplier": _pad(by_lam["histogram"], m)}
            mu = self.local.fields.get("pressure")
            if mu is not None:
                sums = measures.per_sphere_sum(mi, lam, self.local.n_own)
                off = int(halo.total(self.comm, np.array([np.sum(~np.isclose(sums, mu, rtol=1e-9, atol=0))]))[0])
                if off:
                    warn.append(f"the pairs' lambda do not add up to the pressure of {off} spheres: damaged file?")
            alive = alive_lam
        elif self.local.fields.get("contacts") is not None:
            counts = np.asarray(self.local.fields["contacts"], dtype=np.int64)
            hist = measures.count_histogram(self.comm, counts)
            z = float(np.dot(np.arange(len(hist)), hist)) / self.n
            summary["by_multiplier"] = {"Z": z, "rattlers_first_pass": int(hist[:self.dim + 1].sum()),
                                        "source": "the snapshot's per-sphere contacts (lambda_ij > 0); "
                                                  "no pairs in the file: rattlers not removed"}
            m = max(len(hist), len(table["contacts"]))
            table = {"contacts": np.arange(m), "spheres_by_gap": _pad(by_gap["histogram"], m),
                     "spheres_by_multiplier": _pad(hist, m)}
        else:
            warn.append("the file holds no contact multipliers: only the gap network is measured")
        if self.container is not None:
            summary["walls"] = self.wall_contacts(gap, warn)
        rattler_gids = self.local.gid[:self.local.n_own][~alive]
        return Measure("contacts", summary, table, picture=None, warnings=warn), rattler_gids

    def wall_contacts(self, gap, warn):
        """The spheres touching a wall: wall_force > 0 (the snapshot's field: sum_w lambda_iw)
        and gap s_iw - r_i < gap r_i; their count and the mean and largest wall force."""
        n = self.local.n_own
        x, r = self.local.x[:n], 0.5 * self.local.diam[:n]
        s = box.gaps(self.container.walls, x)
        by_gap = (s - r[:, None] < gap * r[:, None]).any(axis=1) if n else np.zeros(0, bool)
        out = {"by_gap": int(halo.total(self.comm, np.array([by_gap.sum()]))[0])}
        wf = self.local.fields.get("wall_force")
        if wf is None:
            warn.append("the file holds no wall_force (a checkpoint, or a run before containers): "
                        "wall contacts by gap only")
            return out
        wf = np.asarray(wf, dtype=np.float64)
        touching = wf > 0
        k = int(halo.total(self.comm, np.array([touching.sum()]))[0])
        total = halo.exact_total(self.comm, wf[touching])
        top = float(self.comm.allreduce(np.array([wf.max() if len(wf) else 0.0]), "max")[0])
        out.update({"by_wall_force": k, "share": k / self.n, "total_wall_force": total,
                    "mean_wall_force": total / k if k else math.nan, "max_wall_force": top})
        return out

    def pressure(self):
        mu = self.local.fields.get("pressure")
        if mu is None:
            return None
        mu = np.asarray(mu, dtype=np.float64)
        total, total2 = halo.exact_totals(self.comm, [mu, mu * mu])
        zero = int(halo.total(self.comm, np.array([(mu <= 0).sum()]))[0])
        mean = total / self.n
        std = math.sqrt(max(total2 / self.n - mean * mean, 0.0))
        top = float(self.comm.allreduce(np.array([mu.max() if len(mu) else 0.0]), "max")[0])
        edges = np.linspace(0.0, top if top > 0 else 1.0, 51)
        hist = halo.total(self.comm, np.histogram(mu, bins=edges)[0])
        summary = {"mean": mean, "std": std, "max": top, "spheres_without_contact_force": zero,
                   "max_over_mean": top / mean if mean > 0 else math.nan}
        picture = self.picture_rows({"pressure": mu})
        return Measure("pressure", summary, {"mu_from": edges[:-1], "mu_to": edges[1:], "spheres": hist},
                       picture=picture, warnings=self.quality_warnings())

    def gr(self, r_max=None, bins=200):
        """g(r) up to r_max (default 5 mean diameters, or half the bulk radius in a smaller
        cluster, so that the inner half of the bulk gives the centres)."""
        _, _, (value, _, r_to) = self.plateau()
        r_bulk = r_to if math.isfinite(r_to) else 0.7 * self.r_cluster
        r_max = min(5.0 * self.d_mean, 0.5 * r_bulk) if r_max is None else float(r_max)
        edges = np.linspace(0.0, r_max, bins + 1)
        g, counts, n_centres, rho = measures.pair_distribution(self.comm, self.local, self.xbar, r_bulk, edges)
        mid = 0.5 * (edges[1:] + edges[:-1])
        warn = self.quality_warnings()
        if n_centres == 0:
            warn.append(f"no interior sphere: the bulk radius {r_bulk:.3g} is not larger than r_max {r_max:.3g}")
            peak_r = peak_g = math.nan
        else:
            near = np.where(mid <= FIRST_PEAK_WINDOW * self.d_mean, g, -np.inf)
            k = int(np.nanargmax(near))
            peak_r, peak_g = float(mid[k]), float(g[k])
        summary = {"r_max": r_max, "bins": bins, "centres": n_centres, "bulk_radius": r_bulk,
                   "number_density": rho, "first_peak_r": peak_r, "first_peak_r_over_d": peak_r / self.d_mean,
                   "first_peak_g": peak_g, "first_peak_window_over_d": FIRST_PEAK_WINDOW,
                   "normalisation": "interior centres only: |X_i - Xbar| <= bulk radius - r_max, the bulk "
                                    "radius being the outer end of the density plateau (every k-th by gid "
                                    f"when there are more than {measures.GR_CENTRES}); rho = spheres per "
                                    "volume of the bulk ball"}
        return Measure("gr", summary, {"r_from": edges[:-1], "r_to": edges[1:], "r_over_d": mid / self.d_mean,
                                       "g": g, "pairs": counts},
                       picture={"r": mid / self.d_mean, "g": g}, warnings=warn)

    def order(self, factor=1.1, exclude_rattlers=False, gap=1e-3):
        i, j, alive, n_counted = self._kept_pairs(factor, exclude_rattlers, gap)
        self_n = n_counted  # means over the spheres counted
        warn = self.quality_warnings()
        if self.dim == 2:
            psi = measures.hexatic(self.local, i, j)
            mod = np.abs(psi)
            sums = halo.exact_totals(self.comm, [mod[alive], psi.real[alive], psi.imag[alive]])
            hist = halo.total(self.comm, np.histogram(mod[alive], bins=np.linspace(0, 1, 21))[0])
            summary = {"factor": factor, "mean_abs_psi6": sums[0] / self_n,
                       "abs_mean_psi6": abs(complex(sums[1], sums[2])) / self_n,
                       "share_above_0.9": float(hist[18:].sum()) / self_n, "spheres": self_n,
                       "rattlers_excluded": bool(exclude_rattlers)}
            table = {"abs_psi6_from": np.linspace(0, 0.95, 20), "spheres": hist}
            picture = self.picture_rows({"abs_psi6": mod, "angle": np.angle(psi) / 6.0})
        elif self.dim == 3:
            q, q6 = measures.steinhardt(self.local, i, j)
            q_all = np.concatenate([q, self.local.refresh(q)])
            q6bar = measures.averaged_q(self.local, i, j, q_all)
            bonds = measures.solid_bonds(self.local, i, j, q_all)
            crystal = (bonds >= measures.SOLID_BONDS)[alive]
            s_q6, s_q6bar = halo.exact_totals(self.comm, [q6[alive], q6bar[alive]])
            n_crystal = int(halo.total(self.comm, np.array([crystal.sum()]))[0])
            edges = np.linspace(0, 0.7, 36)
            h1 = halo.total(self.comm, np.histogram(q6[alive], bins=edges)[0])
            h2 = halo.total(self.comm, np.histogram(q6bar[alive], bins=edges)[0])
            summary = {"factor": factor, "mean_Q6": s_q6 / self_n, "mean_Q6_averaged": s_q6bar / self_n,
                       "crystalline_share": n_crystal / self_n, "solid_bond": measures.SOLID_BOND,
                       "solid_bonds": measures.SOLID_BONDS, "spheres": self_n,
                       "rattlers_excluded": bool(exclude_rattlers)}
            table = {"Q6_from": edges[:-1], "spheres_Q6": h1, "spheres_Q6_averaged": h2}
            picture = self.picture_rows({"Q6": q6})
        else:
            return None
        return Measure("order", summary, table, picture=picture, warnings=warn)

    def force_chains(self):
        """On rank 0: the window's spheres and its contact pairs with lambda (when the file holds
        the pairs), else None."""
        pk = self.packing
        if pk.pairs is None:
            return None
        rows = self.picture_rows()
        gids = self.comm.bcast_object(rows["gid"] if rows is not None else None)
        gi, gj, lam = pk.pairs
        keep = np.isin(gi, gids) & np.isin(gj, gids)
        got = halo.gather_rows(self.comm, {"gi": gi[keep], "gj": gj[keep], "lam": lam[keep]})
        if rows is None:
            return None
        return {**rows, **got}


def _pad(a, m):
    out = np.zeros(m, dtype=np.asarray(a).dtype)
    out[:len(a)] = a
    return out
