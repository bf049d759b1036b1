"""Every tuning constant of the builder, with what it trades.

Lengths are in lattice spacings of the level at hand unless they say otherwise. Changing any
default changes the trees built with it: bump ``BUILDER_VERSION`` (the tree cache keys on it)
and re-measure with ``scripts/bench_build.py`` (figures in BENCHMARKS.md).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

# Bumped whenever the same input and parameters give another tree (the tree cache keys on it).
BUILDER_VERSION = 15


@dataclass(frozen=True)
class BuildParams:
    """Tuning constants of ``mjist.build`` (the defaults are what the benchmarks measure)."""

    # --- lattice -------------------------------------------------------------------------
    #: Level-0 lattice points along the longest axis (within a factor sqrt(2): ``fine_ratio``).
    level0_cells: int = 96
    #: With max_error the level-0 spacing is the power-of-two multiple of max_error / fine_ratio
    #: nearest to extent / level0_cells, so one level sits at that spacing whatever the mesh's
    #: size. The finest band level places most spheres, and how many depends on its spacing
    #: against the target: nearer 1 leaves more for a next level, farther from it places spheres
    #: smaller than needed; both give more leaves for the same ε.
    fine_ratio: float = 1.3
    #: Lattice levels at most (each halves the spacing).
    max_levels: int = 12
    # --- candidate band of a level ------------------------------------------------------------
    #: Half-width of the cube of candidate points around each seed (the centroid of a surface
    #: patch still too far from the spheres). Wider: more band points to evaluate, no better ε.
    band_width: float = 1.0
    #: Seeds move this far into the solid (new spheres touch the surface from inside; a cube
    #: centred on the surface is half outside).
    seed_inset: float = 0.5
    #: Of each cube, only points at least this far behind the seed's tangent plane: the others
    #: are outside or nearer the surface than a new sphere's radius (half a spacing).
    band_min_depth: float = 0.25
    # --- sparse=True --------------------------------------------------------------------------
    #: On levels with spacing between cover_min_h and 2 times the target, keep only spheres that
    #: cover a gap seed (there a band of lattice-sized spheres covers each seed many times over);
    #: finer levels only fill sharp features, where the flat-surface reach of the test is wrong.
    cover_min_h: float = 0.25
    # --- certificate resolution ---------------------------------------------------------------
    #: A sub-triangle whose bound is above the target but every vertex gap below it is uncertain
    #: and is split down to this size: a loose bound of a coarse sub-triangle would otherwise put
    #: spheres where the gap is already small (more leaves), a finer split costs time.
    cert_min_size: float = 0.25
    #: A sub-triangle open for certain is split only down to this size: its seed's band cube
    #: (band_width) must meet its neighbours'. Finer: same leaves, slower certification.
    bad_size: float = 2.0
    # --- stalled triangles --------------------------------------------------------------------
    #: A triangle whose certified gap has not shrunk by stall_gain over stall_levels levels, on a
    #: lattice finer than stall_h times the target, has no solid behind it that a sphere could
    #: fill (the fin of a self-intersecting surface). Refinement stops there and its gap stays in
    #: ε; without this such a fin drives the lattice down towards nothing. Fewer levels or a
    #: coarser stall_h give up on thin plates that a finer lattice still fills.
    stall_gain: float = 0.01
    stall_levels: int = 3
    stall_h: float = 1.0 / 16.0  # times the target
    # --- packing ------------------------------------------------------------------------------
    #: Level 0 keeps grown spheres down to this radius (level-0 spacings): its holes are the deep
    #: interior, which no later level visits. Smaller: more small deep leaves, more coverage.
    level0_r_min: float = 0.125
    #: Band half-width around interior gap points (min_coverage): the gaps need the wider choice.
    fill_band_width: float = 2.0
    #: The interior fill stops below this spacing / max_error once the surface is done: finer
    #: doubles the leaves for a fraction of a percent of coverage.
    fill_min_h: float = 0.5  # times the target
    #: Band keys of one level at most (8 bytes each, ~3x that at the dilation's peak): a level
    #: past it stops refinement with a warning instead of running out of memory.
    max_band_points: int = 120_000_000
    #: Band points decoded and evaluated at a time: memory against per-chunk overhead.
    band_chunk: int = 4_000_000
    #: Relative radius shrink against rounding overlaps between touching spheres.
    shrink: float = 1e-9
    # --- error bound --------------------------------------------------------------------------
    #: The final bound is tightened until within tight_rel of a gap found on the surface, or
    #: within tight_rel_met once the levels certified max_error: where the gap is flat near its
    #: maximum a 5 % walk can take minutes for a few percent of ε.
    tight_rel: float = 0.05
    tight_rel_met: float = 0.2
    #: Default max_error, relative to the bounding-box diagonal.
    default_rel_error: float = 5e-3

    def as_dict(self) -> dict:
        return asdict(self)


DEFAULT = BuildParams()
