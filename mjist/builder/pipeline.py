"""The build pipeline: mesh → lattice levels of inner spheres → hierarchy → certified tree.

``build`` validates its arguments and runs ``_Build``, which holds what the levels share (the
spheres so far, each triangle's certificate, the triangles still open) and runs one lattice
level at a time as three named stages:

* ``certify``: which triangles are still farther than the target from the spheres, and the
  seed points (centroids of their open sub-triangles) that the level's band is built around;
* ``band``: the level's candidate lattice points near the seeds, with their free distances
  (to the surface and to the spheres already placed);
* ``pack``: spheres grown from the candidates (``packing.grown_pack``).

Level 0 packs the whole interior lattice. After the levels, ``hierarchy`` wraps the leaves in
a Batch-Neural-Gas tree and ``bound`` certifies ε. Each stage is timed by the pipeline: the
tree's ``timings`` hold the totals and ``info["levels"]`` the per-level split.
"""
from __future__ import annotations

import hashlib
import time
import warnings
from contextlib import contextmanager

import numpy as np
import trimesh

from ..geometry.bvh import BVH
from ..geometry.mesh import load_mesh
from ..tree import InnerSphereTree
from .bound import certify_faces, restrict_paths, surface_gaps, tight_bound
from .hierarchy import build_hierarchy
from .packing import NO_SEEDS, band_free_distance, grown_pack, seed_grid
from .params import BUILDER_VERSION, DEFAULT, BuildParams
from .voxelize import Voxelizer, decode, encode

__all__ = ["BUILDER_VERSION", "BuildParams", "build", "level0_spacing", "sphere_tree"]


class _Progress:
    """Stage progress on stderr (tqdm), silent unless asked."""

    def __init__(self, enabled: bool, total: int):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="stage", leave=False, dynamic_ncols=True)

    def stage(self, name: str):
        if self.bar is not None:
            self.bar.set_description(name)

    def step(self, info: str = ""):
        if self.bar is not None:
            if info:
                self.bar.set_postfix_str(info)
            self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def build(
    mesh,
    *,
    max_error: float | None = None,
    leaves: int | None = None,
    branching: int = 4,
    seed: int = 0,
    repair: bool = False,
    max_deviation: float | None = None,
    min_coverage: float | None = None,
    sparse: bool = False,
    progress: bool = False,
    params: BuildParams = DEFAULT,
) -> InnerSphereTree:
    """Build an Inner Sphere Tree of a closed triangle mesh.

    Parameters
    ----------
    mesh : path, trimesh.Trimesh or (vertices, faces)
        A closed, consistently wound surface (several shells are fine). Units are the
        mesh's own; ``max_error`` and all results are in the same units.
    max_error : float, optional
        Target for the certified error bound ε (max distance from the surface to the
        spheres). Default: 0.5 % of the bounding-box diagonal (when ``leaves`` is not given).
    leaves : int, optional
        Stop packing after this many leaf spheres (largest first). With ``max_error``
        too, packing stops at whichever comes first.
    branching : int
        Children per inner node (Batch Neural Gas prototypes), 2..16.
    seed : int
        Seed of the clustering; same mesh + parameters + seed gives the same tree.
    repair : bool
        Fix degenerate faces, winding and inversion, and close an open or many-piece surface
        (see ``load_mesh``); ε is certified for the closed surface, and ``info["closure"]``
        says how far that is from the input (add it to ε against the input).
    max_deviation : float, optional
        With ``repair``: the farthest the closing may move an input vertex (mesh units).
    min_coverage : float, optional
        Also fill the interior gaps between spheres, level by level, until the leaves fill
        this fraction of the mesh volume (e.g. 0.9) or the lattice reaches the resolution the
        surface needs. Without it only the band near the surface is refined (what distance
        queries need); the interior fill adds many small deep leaves and makes the
        penetration volume closer to the true overlap volume.
    sparse : bool
        Near the surface keep only the spheres that close a gap still above ``max_error``
        (needs ``max_error``; not with ``min_coverage``). Same certified ε with fewer leaves,
        so smaller and faster-to-query trees, but the sphere surface is bumpier between the
        certified worst points (larger mean gap): for distance and contact queries, not for
        bodies resting on each other in a simulation (a clenched jaw rocks between contact sets).
    progress : bool
        Show a progress bar per stage on stderr.
    params : BuildParams
        Tuning constants (``mjist.builder.params``); the defaults are what the benchmarks measure.

    Returns
    -------
    InnerSphereTree
        With ``error_bound`` certified (see ``mjist.builder.bound``) and ``coverage``.

    Raises
    ------
    MeshError
        The mesh is not a closed solid (see ``load_mesh``).
    ValueError
        Parameters out of range (``max_error`` not positive or absurd for the mesh size).
    """
    if not 2 <= int(branching) <= 16:
        raise ValueError(f"branching={branching} must be between 2 and 16")
    if leaves is not None and int(leaves) < 1:
        raise ValueError(f"leaves={leaves} must be at least 1")
    if min_coverage is not None and not 0.0 < float(min_coverage) < 1.0:
        raise ValueError(f"min_coverage={min_coverage} must be a fraction of the volume in (0, 1), e.g. 0.9")
    bar = _Progress(progress, 5)
    t0 = time.perf_counter()
    bar.stage("load + validate")
    m = load_mesh(mesh, repair=repair, max_deviation=max_deviation)
    load_s = time.perf_counter() - t0
    bar.step(f"{len(m.faces)} faces, {m.shells} shell(s)")
    max_error = _check_target(m, max_error, leaves, params)
    if sparse and (max_error is None or min_coverage is not None):
        raise ValueError("sparse=True needs max_error (the gap it keeps spheres for) and no min_coverage (which wants volume)")
    run = _Build(m, max_error, leaves, min_coverage, sparse, params)
    run.timings["load"] = load_s
    bar.stage("voxelize + pack")
    run.levels()
    bar.step(f"{len(run.R)} spheres, {run.last_level + 1} levels")
    bar.stage("hierarchy (batch neural gas)")
    with run.timed("hierarchy"):
        arrays = _assemble(run.C, run.R, int(branching), int(seed))
    bar.step(f"{len(arrays['radii'])} nodes, depth {int(arrays['depth_of'].max())}")
    bar.stage("error bound")
    eps, eps_lo, mean_gap = run.bound(int(seed))
    run.timings["total"] = time.perf_counter() - t0
    bar.step(f"eps {eps:.3g}")
    bar.close()
    run.warn(eps)
    user = {"max_error": max_error, "leaves": leaves, "branching": int(branching), "seed": int(seed), "repair": bool(repair),
            "min_coverage": None if min_coverage is None else float(min_coverage), "sparse": bool(sparse)}
    if max_deviation is not None:
        user["max_deviation"] = float(max_deviation)
    return InnerSphereTree(
        **arrays, error_bound=float(eps), error_lower=float(eps_lo), mesh_volume=m.volume, mesh_hash=m.content_hash,
        params=user, timings=run.timings, info=run.info(mean_gap),
    )


def _check_target(m, max_error, leaves, params: BuildParams) -> float | None:
    """``max_error`` with its default, checked against the mesh's size (a unit mix-up shows there)."""
    ext = m.extents
    diag = float(np.linalg.norm(ext))
    if max_error is None and leaves is None:
        max_error = params.default_rel_error * diag
    if max_error is None:
        return None
    max_error = float(max_error)
    if not np.isfinite(max_error) or max_error <= 0:
        raise ValueError(f"max_error={max_error} must be a positive number (mesh units)")
    if max_error >= 0.25 * float(ext.max()):
        raise ValueError(
            f"max_error={max_error:g} is not small against the mesh (largest extent {ext.max():g}): "
            "check the units (a mesh in metres needs max_error in metres, e.g. 5e-5 for 0.05 mm)"
        )
    if max_error < 1e-6 * diag:
        raise ValueError(
            f"max_error={max_error:g} is below 1e-6 of the mesh size ({diag:g}): "
            "check the units (a mesh in millimetres needs max_error in millimetres)"
        )
    return max_error


class _Build:
    """One build's state across its lattice levels (see the module docstring for the stages)."""

    def __init__(self, m, max_error, leaves, min_coverage, sparse: bool, params: BuildParams):
        self.m = m
        self.p = params
        self.max_error = max_error
        self.target = max_error if max_error is not None else 0.0
        self.min_coverage = min_coverage
        self.fill = min_coverage is not None
        self.sparse = sparse
        self.max_leaves = int(leaves) if leaves is not None else np.iinfo(np.int64).max
        self.diag = float(np.linalg.norm(m.extents))
        self.timings = {"load": 0.0, "voxelize": 0.0, "pack": 0.0}
        self.level_log = []
        self.last_level = 0
        nf = len(m.faces)
        self.certified = np.inf  # best bound so far (stays valid as spheres are added)
        self.face_ub = np.full(nf, np.inf)  # per-triangle certificates, also valid from then on
        self.open_faces = np.arange(nf, dtype=np.int64)  # triangles not yet below the target
        self.open_paths = None  # their sub-triangles still above it (bound.certify_faces)
        self.ub_before = [np.full(nf, np.inf)] * params.stall_levels  # face_ub 1..stall_levels levels back
        self.stalled = np.empty(0, np.int64)  # triangles given up on (see BuildParams.stall_gain)
        self.sph_bvh, self.sph_n = None, -1  # the sphere BVH of the current level, over the first sph_n spheres

    @contextmanager
    def timed(self, name: str, log: dict | None = None):
        """Add the block's seconds to ``timings[name]`` (and to the level's ``log``)."""
        t = time.perf_counter()
        try:
            yield
        finally:
            dt = time.perf_counter() - t
            self.timings[name] = self.timings.get(name, 0.0) + dt
            if log is not None:
                log[f"{name}_seconds"] = log.get(f"{name}_seconds", 0.0) + dt

    # ---- the levels --------------------------------------------------------------------------

    def levels(self) -> None:
        """Level 0, then one band level at a time until the surface is certified (or a limit)."""
        self.level0()
        self.inward = self._inward_normals()
        for level in range(1, self.p.max_levels + 1):
            if len(self.R) >= self.max_leaves:
                break
            log = {"level": level, "spacing": self.vox.spacing(level)}
            t_level = time.perf_counter()
            with self.timed("certify", log):
                seeds, seed_n, seed_depth, ub = self.certify(self.vox.spacing(level))
            log["certify_bound"] = float(ub) if np.isfinite(ub) else None
            if not self.refine_more(seeds, ub, self.vox.spacing(level)):
                log["seconds"] = time.perf_counter() - t_level
                self.level_log.append(log)  # the certificate that ended the levels, nothing placed
                break
            if self.surface_done:
                seeds, seed_n = seeds[:0], seed_n[:0]
            with self.timed("voxelize", log):
                band = self.band(level, seeds, seed_n, seed_depth)
            if band is None:
                break
            P, f, keys, n_band = band
            with self.timed("pack", log):
                n_new = self.pack(self.vox.spacing(level), P, f, keys, seeds)
            self.last_level = level
            log.update({"open_faces": int(len(self.open_faces)), "seeds": int(len(seeds)), "band_points": int(n_band),
                        "candidates": int(len(P)), "spheres": n_new, "seconds": time.perf_counter() - t_level})
            self.level_log.append(log)
        if len(self.R) == 0:
            raise ValueError(
                "no inner sphere fits: the mesh is thinner than the level-0 lattice; "
                "pass a smaller max_error or check the mesh"
            )

    def level0(self) -> None:
        """The whole interior lattice at the coarsest spacing, packed with grown spheres."""
        m, p = self.m, self.p
        log = {"level": 0}
        t = time.perf_counter()
        with self.timed("voxelize", log):
            h0 = level0_spacing(float(m.extents.max()), self.max_error, p)
            self.vox = Voxelizer(m.vertices, m.faces, h0)
            P, D = self.vox.level0()
        with self.timed("pack", log):
            keys = encode(np.rint((P - self.vox.origin) / h0).astype(np.int64))
            f = D.copy()
            r_min0 = p.level0_r_min * h0
            self.C, self.R = grown_pack(P, f, keys, self.vox.origin, h0, r_min0, self.max_leaves, p.shrink, self.vox)
        # interior fill: lattice points left in the holes between spheres (free distance gap_f)
        # seed the first level whose smallest sphere fits there
        self.filled = 4.0 / 3.0 * np.pi * float(np.sum(self.R**3))
        hole = (f >= 0.5 * r_min0) & (f < r_min0)  # (f >= r_min0: the spheres' own centres)
        self.gaps = P[hole] if self.fill else np.empty((0, 3))
        self.gap_f = f[hole] if self.fill else np.empty(0)
        log.update({"spacing": h0, "band_points": int(len(P)), "spheres": int(len(self.R)), "seconds": time.perf_counter() - t})
        self.level_log.append(log)

    def _inward_normals(self) -> np.ndarray:
        """Unit inward normal of each face where the solid lies behind it, else zero."""
        m = self.m
        tri = m.vertices[m.faces]
        inward = -np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm = np.linalg.norm(inward, axis=1)[:, None]
        inward = np.divide(inward, nrm, out=np.zeros_like(inward), where=nrm > 0)
        # the solid lies behind a face only where the winding number is 0 in front of it and 1
        # behind; elsewhere (crossed faces, the inverted sliver of a fin, shells overlapping) a zero
        # normal keeps the seed's whole cube
        inward[self.vox.side != 0] = 0.0
        return inward

    def certify(self, h: float):
        """Certify the open triangles against the spheres so far; the level's seeds.

        Returns ``(seeds, seed normals, seed depth, bound)``: the centroids of the
        sub-triangles still above the target, their faces' inward normals, how far inside the
        surface they sit, and the certified bound over the whole surface.
        """
        m, p = self.m, self.p
        self.sph_bvh = BVH.of_spheres(self.C, self.R) if len(self.R) else None
        self.sph_n = len(self.R)  # C and R only grow: the same length is the same spheres
        if not len(self.R):
            return m.vertices[m.faces].mean(axis=1), self.inward, 0.0, np.inf
        open_faces = self.open_faces
        ub_f, _, seeds, paths = certify_faces(
            m.vertices, m.faces, open_faces, self.C, self.R, self.target, p.cert_min_size * h, want_seeds=True,
            bvh=self.sph_bvh, seed_inset=p.seed_inset * h, prev=self.open_paths, bad_size=p.bad_size * h,
        )
        self.face_ub[open_faces] = ub_f
        seed_n = self.inward[np.repeat(open_faces, np.diff(paths[1]))]  # each seed's face's
        stuck = ((ub_f > self.target) & (ub_f > (1.0 - p.stall_gain) * self.ub_before[-1][open_faces])
                 & (h <= p.stall_h * self.target))
        self.stalled = np.concatenate([self.stalled, open_faces[stuck]])
        self.ub_before = [self.face_ub.copy()] + self.ub_before[:-1]
        still = np.flatnonzero((ub_f > self.target) & ~stuck)
        if stuck.any():  # no more seeds there
            keep = np.repeat(~stuck, np.diff(paths[1]))
            seeds, seed_n = seeds[keep], seed_n[keep]
        self.open_faces = open_faces[still]
        self.open_paths = restrict_paths(paths, still)  # next level walks only what is still open
        return seeds, seed_n, p.seed_inset * h, float(self.face_ub.max())

    def refine_more(self, seeds, ub: float, h: float) -> bool:
        """Record the level's certificate; whether the level has anything to place."""
        self.certified = min(self.certified, ub)
        self.surface_done = ub <= self.target or len(seeds) == 0
        if self.fill and (self.filled >= self.min_coverage * self.m.volume
                          or (self.surface_done and h < self.p.fill_min_h * self.target)):
            self.gaps, self.gap_f = self.gaps[:0], self.gap_f[:0]  # covered enough, or finer than the surface needs
        if self.surface_done and len(self.gaps) == 0:
            return False
        return h >= 1e-7 * self.diag

    def band(self, level: int, seeds, seed_n, seed_depth):
        """The level's candidates ``(points, free distances, keys, band size)``; None past the band limit."""
        p, vox = self.p, self.vox
        h = vox.spacing(level)
        r_min = 0.5 * h
        now = self.gap_f >= r_min
        band = vox.band_keys(level, (self.gaps[now], p.fill_band_width * h),
                             oriented=(seeds, p.band_width * h, seed_n, seed_depth, p.band_min_depth * h))
        self.gaps, self.gap_f = self.gaps[~now], self.gap_f[~now]  # holes too small for this level: a finer one
        n_band = len(band)
        if n_band > p.max_band_points:
            warnings.warn(
                f"lattice level {level} would need {n_band} band points (limit {p.max_band_points}); "
                "stopping refinement: pass a larger max_error or a leaves= limit",
                RuntimeWarning,
                stacklevel=4,
            )
            return None
        # the band in chunks (its free distances only depend on the spheres of earlier levels):
        # memory holds the keys and the candidates, not the whole band's points
        parts, gap_parts = [], [(self.gaps, self.gap_f)]
        for s in range(0, n_band, p.band_chunk):
            kc = band[s:s + p.band_chunk]
            Pc = decode(kc, vox.origin, h)
            fc = band_free_distance(Pc, vox, self.C, self.R, r_min, bvh=self.sph_bvh)
            if self.fill:  # points too tight for this level may hold a sphere of the next one
                hole = (fc >= 0.5 * r_min) & (fc < r_min)
                gap_parts.append((Pc[hole], fc[hole]))
            keep = fc >= r_min
            parts.append((Pc[keep], fc[keep], kc[keep]))
        del band
        P = np.concatenate([q[0] for q in parts]) if parts else np.empty((0, 3))
        f = np.concatenate([q[1] for q in parts]) if parts else np.empty(0)
        keys = np.concatenate([q[2] for q in parts]) if parts else np.empty(0, np.int64)
        if self.fill:
            self.gaps = np.concatenate([q[0] for q in gap_parts])
            self.gap_f = np.concatenate([q[1] for q in gap_parts])
        return P, f, keys, n_band

    def pack(self, h: float, P, f, keys, seeds) -> int:
        """Grow the level's spheres from its candidates; returns how many it placed."""
        p = self.p
        r_min = 0.5 * h
        # spheres only where they close a gap (not with the interior fill, which wants volume);
        # a seed lies seed_inset*h inside the surface, so reaching it within target - that
        # inset puts the surface point above it within target
        cover = self.sparse and p.cover_min_h * self.target <= h < self.target / p.seed_inset
        reach = self.target - p.seed_inset * h
        grid = seed_grid(seeds, self.vox.origin, max(self.target, h), reach) if cover else NO_SEEDS
        Cn, Rn = grown_pack(P, f, keys, self.vox.origin, h, r_min, self.max_leaves - len(self.R), p.shrink, self.vox,
                            prior=(self.C, self.R, self.sph_bvh), seeds=grid)
        if self.fill:
            hole = (f >= 0.5 * r_min) & (f < r_min)
            self.gaps = np.concatenate([self.gaps, P[hole]])
            self.gap_f = np.concatenate([self.gap_f, f[hole]])
            self.filled += 4.0 / 3.0 * np.pi * float(np.sum(Rn**3))
        self.C = np.concatenate([self.C, Cn])
        self.R = np.concatenate([self.R, Rn])
        return int(len(Rn))

    # ---- after the levels --------------------------------------------------------------------

    def bound(self, seed: int) -> tuple[float, float, float]:
        """The certified ε, the gap found on the surface (a lower bound of ε), the mean gap."""
        m, p = self.m, self.p
        t = time.perf_counter()
        # the leaves in packing order: one BVH for both passes (the last level's when the loop
        # ended before adding spheres, the usual case: its certificate found the surface done)
        leaf_bvh = self.sph_bvh if self.sph_bvh is not None and self.sph_n == len(self.R) else BVH.of_spheres(self.C, self.R)
        # once the target is certified, tightening ε below it needs less: where the gap is flat
        # near its maximum (many grown spheres hugging a coarse surface) a 5 % walk takes minutes
        rel = p.tight_rel_met if self.certified <= self.target else p.tight_rel
        eps, eps_lo = tight_bound(m.vertices, m.faces, self.C, self.R, rel_tol=rel, known=self.certified, bvh=leaf_bvh,
                                  face_ub=self.face_ub)
        mean_gap = float(surface_gaps(m.vertices, m.faces, self.C, self.R, seed=seed, bvh=leaf_bvh).mean())
        # the levels' certificates are part of the bound's cost
        self.timings["bound"] = time.perf_counter() - t + self.timings.pop("certify", 0.0)
        return eps, eps_lo, mean_gap

    def warn(self, eps: float) -> None:
        """Say why ε stayed above max_error, or why the coverage was not reached."""
        m, max_error = self.m, self.max_error
        self.stalled = self.stalled[self.face_ub[self.stalled] > self.target]
        stalled = self.stalled
        more_allowed = len(self.R) < self.max_leaves
        if max_error is not None and eps > max_error and len(stalled) and more_allowed:
            worst = stalled[np.argmax(self.face_ub[stalled])]
            warnings.warn(
                f"certified error bound {eps:.4g} exceeds max_error={max_error:.4g}: {len(stalled)} triangles "
                f"(worst {worst}, gap <= {min(self.face_ub[worst], eps):.4g}, near "
                f"{np.round(m.vertices[m.faces[worst]].mean(axis=0), 6).tolist()}) "
                "stay open however fine the lattice: the solid beside them is thinner than the lattice reaches "
                "(a fin or plate of a segmentation, often where its two sides cross). ε counts them, so it stays a "
                "true bound for this mesh; thicken or remove those fins (e.g. MeshLab's 'select self intersecting "
                "faces', pymeshfix) to reach max_error",
                RuntimeWarning,
                stacklevel=3,
            )
        elif max_error is not None and eps > max_error and more_allowed:
            warnings.warn(
                f"certified error bound {eps:.4g} exceeds max_error={max_error:.4g} after {self.last_level + 1} "
                "lattice levels (thin features narrower than the finest lattice?)",
                RuntimeWarning,
                stacklevel=3,
            )
        if self.fill and self.filled < self.min_coverage * m.volume and more_allowed:
            warnings.warn(
                f"min_coverage={self.min_coverage:g} not reached: the leaves fill {self.filled / m.volume:.1%} of the "
                f"volume ({len(self.R)} leaves) when the lattice reached the surface's resolution; the gaps left are "
                "finer than max_error (pass a smaller max_error to fill further)",
                RuntimeWarning,
                stacklevel=3,
            )

    def info(self, mean_gap: float) -> dict:
        m, stalled = self.m, self.stalled
        return {
            "builder_version": BUILDER_VERSION,
            "mesh_vertices": int(len(m.vertices)),
            "mesh_faces": int(len(m.faces)),
            "mesh_shells": int(m.shells),
            "mesh_area": m.area,
            "lattice_levels": self.last_level + 1,
            "finest_spacing": self.vox.spacing(self.last_level),
            "points_evaluated": int(self.vox.points_evaluated),
            "repairs": list(m.repairs),
            "closure": m.closure.as_dict() if m.closure is not None else None,
            "mean_gap": mean_gap,
            "crossed_faces": int(self.vox.crossed_faces),
            "stalled_faces": int(len(stalled)),
            "stalled_area": float(trimesh.triangles.area(triangles=m.vertices[m.faces[stalled]]).sum()) if len(stalled) else 0.0,
            "levels": self.level_log,
        }


def level0_spacing(extent: float, max_error: float | None, params: BuildParams = DEFAULT) -> float:
    """Level-0 lattice spacing of a mesh whose longest extent is ``extent``.

    ``extent / level0_cells`` without a target; with one, the spacing ``max_error / fine_ratio
    * 2**L`` nearest to it (integer ``L``, so within a factor sqrt(2): 68 to 136 cells), which
    puts lattice level ``L`` at ``max_error / fine_ratio``.
    """
    h0 = extent / params.level0_cells
    if max_error is None:
        return h0
    fine = max_error / params.fine_ratio
    return fine * 2.0 ** int(np.round(np.log2(h0 / fine)))


def _leaf_order(C, R):
    """``np.lexsort((C[:, 2], C[:, 1], C[:, 0], -R))``, with the coordinates looked at only among
    equal radii (grown spheres rarely tie, and a full lexsort of millions of leaves is slow)."""
    order = np.argsort(-R, kind="stable")
    Rs = R[order]
    eq = Rs[1:] == Rs[:-1]
    if eq.any():
        tied = np.zeros(len(R), bool)
        tied[:-1] |= eq
        tied[1:] |= eq
        pos = np.flatnonzero(tied)
        group = np.concatenate([[0], np.cumsum(~eq)])[pos]  # runs of equal radii keep their slots
        sub = order[pos]
        order[pos] = sub[np.lexsort((C[sub, 2], C[sub, 1], C[sub, 0], group))]
    return order


def _assemble(C, R, branching, seed):
    """Hierarchy arrays (``InnerSphereTree`` fields) over leaf spheres ``C, R``."""
    # determinism: order leaves by (radius desc, then coordinates) before clustering
    order = _leaf_order(C, R)
    C, R = np.ascontiguousarray(C[order]), np.ascontiguousarray(R[order])
    (centers, radii, cstart, ccount, parent, depth, lstart, lend, perm) = build_hierarchy(C, R, branching, seed)
    leaf_node = np.empty(len(R), np.int64)
    is_leaf = ccount == 0
    leaf_node[lstart[is_leaf]] = np.flatnonzero(is_leaf)
    return {
        "centers": centers, "radii": radii, "child_start": cstart, "child_count": ccount,
        "parent": parent, "depth_of": depth, "leaf_start": lstart, "leaf_end": lend,
        "leaf_centers": np.ascontiguousarray(C[perm]), "leaf_radii": np.ascontiguousarray(R[perm]),
        "leaf_node": leaf_node,
    }


def sphere_tree(centers, radii, *, branching: int = 4, seed: int = 0) -> InnerSphereTree:
    """An Inner Sphere Tree over given spheres: the object *is* their union (ε = 0).

    For tools and probes made of spheres (a haptic probe tip is one sphere) and for tests.
    Spheres should not overlap each other, or ``penetration_volume`` counts the overlap twice.

    Parameters
    ----------
    centers : array (n, 3)
    radii : array (n,)
        Positive radii.
    """
    C = np.array(centers, dtype=np.float64, ndmin=2)
    R = np.array(radii, dtype=np.float64, ndmin=1)
    if C.ndim != 2 or C.shape[1] != 3 or R.shape != (C.shape[0],) or len(R) == 0:
        raise ValueError(f"sphere_tree needs centers (n, 3) and radii (n,) with n >= 1, got {C.shape} and {R.shape}")
    if not (np.isfinite(C).all() and np.isfinite(R).all() and (R > 0).all()):
        raise ValueError("sphere_tree needs finite centers and finite positive radii")
    if not 2 <= int(branching) <= 16:
        raise ValueError(f"branching={branching} must be between 2 and 16")
    arrays = _assemble(C, R, int(branching), int(seed))
    h = hashlib.sha256(C.tobytes() + R.tobytes()).hexdigest()
    return InnerSphereTree(
        **arrays,
        error_bound=0.0,
        error_lower=0.0,
        mesh_volume=float(4.0 / 3.0 * np.pi * np.sum(R**3)),
        mesh_hash=h,
        params={"branching": int(branching), "seed": int(seed), "spheres": True},
    )
