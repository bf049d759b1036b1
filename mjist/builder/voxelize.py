"""Voxelize. Candidate sphere centres on nested lattices with their surface distance.

Level 0 is a uniform lattice over the whole bounding box; level ``l`` has spacing
``h0 / 2**l`` and is generated only in a narrow band around the surface regions whose
gap to the spheres is still too large (adaptive refinement: small ε without a billion
voxels). Lattices nest (a level-l point is a level-(l+1) point), all share one origin.

Inside/outside is the nonzero winding number: taken from the face beside the point where no
other face crosses it (``selfintersect``), else by ray casting through a triangle BVH (signed
crossings, retried when a ray grazes an edge or vertex); the distance from the BVH closest point.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import get_num_threads, njit, prange

from ..geometry.bvh import BVH, RAY_DIRS, signed_distance
from ..geometry.selfintersect import crossed_faces, face_sides

KEY_BITS = 21  # lattice coordinates up to 2**21 per axis
KEY_MASK = (1 << KEY_BITS) - 1
LEVEL0_COARSE = 4  # spacings of the coarse lattice that culls level 0's far-outside points


@njit(cache=True)
def encode(ijk):
    """Pack non-negative lattice coordinates ``(n, 3)`` into sortable int64 keys."""
    n = ijk.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        out[i] = (ijk[i, 0] << (2 * KEY_BITS)) | (ijk[i, 1] << KEY_BITS) | ijk[i, 2]
    return out


@njit(cache=True)
def _nearest_points(seeds, origin, h, dims):
    """Lattice coordinates ``(n, 3)`` of the lattice point nearest each seed, clamped to the lattice."""
    n = seeds.shape[0]
    out = np.empty((n, 3), np.int64)
    for s in range(n):
        for d in range(3):
            out[s, d] = min(max(int(np.floor((seeds[s, d] - origin[d]) / h + 0.5)), 0), dims[d] - 1)
    return out


def _seed_keys(seeds, origin, h, dims):
    return encode(_nearest_points(seeds, origin, h, dims))


@njit(cache=True, nogil=True)
def _dilate_sorted(keys, axis, w, dims):
    """Every key shifted by -w..w along one axis (clipped to the lattice), sorted and unique.

    ``keys`` must be sorted and unique. Shifting every key by the same offset along one axis keeps it sorted (the keys that would
    leave the lattice are skipped), so the dilation is the merge of 2w+1 sorted streams, with
    duplicates dropped on the way: linear time, where sorting the (2w+1)x larger band with
    ``np.unique`` took 40 % of the voxelization.
    """
    shift = (2 - axis) * KEY_BITS
    step = np.int64(1) << shift
    n = keys.shape[0]
    k = 2 * w + 1
    head = np.zeros(k, np.int64)
    val = np.empty(k, np.int64)
    top = dims[axis]
    out = np.empty(n * k, np.int64)
    m = 0
    for j in range(k):  # each stream's first key that stays on the lattice
        o = j - w
        i = 0
        while i < n and not 0 <= ((keys[i] >> shift) & KEY_MASK) + o < top:
            i += 1
        head[j] = i
        val[j] = keys[i] + o * step if i < n else -1
    while True:
        best = -1
        bj = -1
        for j in range(k):
            if head[j] < n and (bj < 0 or val[j] < best):
                best = val[j]
                bj = j
        if bj < 0:
            break
        if m == 0 or out[m - 1] != best:
            out[m] = best
            m += 1
        o = bj - w
        i = head[bj] + 1
        while i < n and not 0 <= ((keys[i] >> shift) & KEY_MASK) + o < top:
            i += 1
        head[bj] = i
        if i < n:
            val[bj] = keys[i] + o * step
    return out[:m].copy()  # a view would keep the (2w+1)x buffer alive


def _dilate(keys, axis, w, dims, min_chunk=1_000_000):
    """``_dilate_sorted`` in slabs of the first lattice axis, one thread per slab.

    The keys sort by that axis first, so the slabs' results concatenate in order; a dilation
    along it reads ``w`` layers beyond each slab and keeps only its own layers (numba
    releases the GIL in ``_dilate_sorted``, so the threads run in parallel).
    """
    workers = min(get_num_threads(), len(keys) // min_chunk)
    if workers < 2:
        return _dilate_sorted(keys, axis, w, dims)
    a = keys >> (2 * KEY_BITS)  # first-axis layer of each key (sorted)
    cuts = np.unique(a[(np.arange(1, workers) * len(a)) // workers])
    cuts = np.concatenate([[0], cuts[cuts > 0], [dims[0]]])
    jobs = []
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        reach = w if axis == 0 else 0
        i0, i1 = np.searchsorted(a, [lo - reach, hi + reach])
        jobs.append((keys[i0:i1], np.int64(lo) << (2 * KEY_BITS), np.int64(hi) << (2 * KEY_BITS)))

    def run(job):
        part, klo, khi = job
        out = _dilate_sorted(part, axis, w, dims)
        return out[np.searchsorted(out, klo):np.searchsorted(out, khi)] if axis == 0 else out

    with ThreadPoolExecutor(len(jobs)) as pool:
        return np.concatenate(list(pool.map(run, jobs)))


def sorted_unique(keys):
    """``np.unique`` of int64 keys by a radix sort: numpy >= 2.3's ``np.unique`` goes through a
    hash table first, an order of magnitude slower on millions of lattice keys."""
    keys = np.sort(keys, kind="stable")  # radix sort for integers
    if len(keys) < 2:
        return keys
    keep = np.empty(len(keys), bool)
    keep[0] = True
    np.not_equal(keys[1:], keys[:-1], out=keep[1:])
    return keys[keep]


# --- oriented band: the inner half of each seed's cube ----------------------------------------
#
# A seed lies ``depth`` behind the surface; a new sphere needs a centre at least r_min (half a
# spacing) behind it. Of a seed's cube, the points in front of its tangent plane are outside the
# solid or too near the surface, and the band's free-distance search rejected them one by one
# (about half of a fine level's band; a handful in millions of candidates are lost, where the
# surface curves towards the plane). Where the solid is convex the tangent plane is farther than
# the surface, so a point behind the plane by r_min may still be too near, never the reverse;
# where it is concave ``min_depth`` below r_min leaves room for the surface bending away.


@njit(cache=True)
def _plane_keep(S, N, s, origin, h, a, b, c, depth, min_depth):
    if N[s, 0] == 0.0 and N[s, 1] == 0.0 and N[s, 2] == 0.0:  # no side known: the whole cube
        return True
    return (depth + (origin[0] + a * h - S[s, 0]) * N[s, 0] + (origin[1] + b * h - S[s, 1]) * N[s, 1]
            + (origin[2] + c * h - S[s, 2]) * N[s, 2]) >= min_depth


@njit(cache=True, parallel=True)
def _oriented_counts(S, N, sel, origin, h, dims, w, depth, min_depth, lay_lo, lay_hi, base, cnt):
    """Per seed ``sel[t]`` (lattice point ``base[t]``): how many kept points of its cube lie in
    each of the ``2w + 1`` first-axis layers ``cnt[t]`` (0 outside layers ``lay_lo..lay_hi-1``)."""
    for t in prange(sel.shape[0]):
        s = sel[t]
        for i in range(2 * w + 1):
            a = base[t, 0] + i - w
            k = 0
            if lay_lo <= a < lay_hi:
                for b in range(max(base[t, 1] - w, 0), min(base[t, 1] + w + 1, dims[1])):
                    for c in range(max(base[t, 2] - w, 0), min(base[t, 2] + w + 1, dims[2])):
                        if _plane_keep(S, N, s, origin, h, a, b, c, depth, min_depth):
                            k += 1
            cnt[t, i] = k


@njit(cache=True)
def _layer_slots(base, cnt, w, lay_lo, n_layers):
    """Bucket the kept points by first-axis layer (from ``lay_lo``): each layer's start, each
    seed's write position per layer."""
    layer_n = np.zeros(n_layers + 1, np.int64)
    for t in range(base.shape[0]):
        for i in range(2 * w + 1):
            if cnt[t, i]:
                layer_n[base[t, 0] + i - w - lay_lo + 1] += cnt[t, i]
    for l in range(n_layers):
        layer_n[l + 1] += layer_n[l]
    fill = layer_n[:-1].copy()
    pos = np.empty_like(cnt)
    for t in range(base.shape[0]):
        for i in range(2 * w + 1):
            if cnt[t, i]:
                a = base[t, 0] + i - w - lay_lo
                pos[t, i] = fill[a]
                fill[a] += cnt[t, i]
    return layer_n, pos


@njit(cache=True, parallel=True)
def _oriented_emit(S, N, sel, origin, h, dims, w, depth, min_depth, base, cnt, pos, out):
    for t in prange(sel.shape[0]):
        s = sel[t]
        for i in range(2 * w + 1):
            if cnt[t, i] == 0:
                continue
            a = base[t, 0] + i - w
            q = pos[t, i]
            for b in range(max(base[t, 1] - w, 0), min(base[t, 1] + w + 1, dims[1])):
                for c in range(max(base[t, 2] - w, 0), min(base[t, 2] + w + 1, dims[2])):
                    if _plane_keep(S, N, s, origin, h, a, b, c, depth, min_depth):
                        out[q] = (a << (2 * KEY_BITS)) | (b << KEY_BITS) | c
                        q += 1


# lowest set bit's index of a word: (low * _DEBRUIJN) >> 58 is distinct for each of the 64 bits
_DEBRUIJN = np.uint64(0x03F79D71B4CA8B09)
_DEBRUIJN_POS = np.zeros(64, np.int64)
for _i in range(64):
    _DEBRUIJN_POS[(((1 << _i) * 0x03F79D71B4CA8B09) & 0xFFFFFFFFFFFFFFFF) >> 58] = _i


@njit(cache=True, parallel=True)
def _dedupe_layers(out, layer_n, uniq, pos_table):
    """Each layer's distinct keys, sorted, to the front of its segment (``uniq`` per layer): a
    bitmap over the layer's (second, third axis) box, read back in order (cheaper than sorting
    the ~4x duplicated points)."""
    for l in prange(layer_n.shape[0] - 1):
        seg = out[layer_n[l]:layer_n[l + 1]]
        n = seg.shape[0]
        if n == 0:
            uniq[l] = 0
            continue
        b0 = c0 = 1 << KEY_BITS
        b1 = c1 = -1
        for i in range(n):
            b = (seg[i] >> KEY_BITS) & KEY_MASK
            c = seg[i] & KEY_MASK
            b0, b1, c0, c1 = min(b0, b), max(b1, b), min(c0, c), max(c1, c)
        cols = c1 - c0 + 1
        if (b1 - b0 + 1) * cols > 64 * n + 4096:  # sparse in its box: sort instead
            seg.sort()
            k = 1
            for i in range(1, n):
                if seg[i] != seg[k - 1]:
                    seg[k] = seg[i]
                    k += 1
            uniq[l] = k
            continue
        bits = np.zeros(((b1 - b0 + 1) * cols + 63) // 64, np.uint64)
        for i in range(n):
            q = (((seg[i] >> KEY_BITS) & KEY_MASK) - b0) * cols + (seg[i] & KEY_MASK) - c0
            bits[q >> 6] |= np.uint64(1) << np.uint64(q & 63)
        top = seg[0] & ~((np.int64(1) << (2 * KEY_BITS)) - 1)  # the layer's first-axis bits
        k = 0
        for wi in range(bits.shape[0]):
            word = bits[wi]
            while word != 0:
                low = word & (~word + np.uint64(1))
                q = wi * 64 + pos_table[(low * _DEBRUIJN) >> np.uint64(58)]
                seg[k] = top | ((q // cols + b0) << KEY_BITS) | (q % cols + c0)
                k += 1
                word ^= low
        uniq[l] = k


@njit(cache=True, parallel=True)
def _gather_layers(out, layer_n, start, res):
    for l in prange(layer_n.shape[0] - 1):
        for i in range(start[l + 1] - start[l]):
            res[start[l] + i] = out[layer_n[l] + i]


ORIENTED_CHUNK = 16_000_000  # cube points (before the plane test) generated at a time


def oriented_band(seeds, normals, origin, h, dims, w, depth, min_depth):
    """Sorted unique keys of the points of each seed's cube (``w`` spacings each way) that lie at
    least ``min_depth`` behind its tangent plane: the seed is ``depth`` behind the surface along
    its unit inward normal (a zero normal keeps the whole cube).

    The lattice is cut into slabs of first-axis layers, each holding at most ~``ORIENTED_CHUNK``
    cube points of the seeds that reach it; a slab's points are bucketed by layer (the keys
    sort by that axis first) and each layer deduplicated on its own, in parallel: faster than
    one sort of the ~4x duplicated points, and the memory holds one slab's duplicates, not
    the band's.
    """
    S = np.ascontiguousarray(seeds, dtype=np.float64)
    N = np.ascontiguousarray(normals, dtype=np.float64)
    n_lay = int(dims[0])
    near = _nearest_points(S, origin, float(h), dims)
    order = np.argsort(near[:, 0], kind="stable")
    first = np.searchsorted(near[order, 0], np.arange(n_lay + 1))  # each layer's seeds in ``order``
    budget = max(ORIENTED_CHUNK // (2 * w + 1) ** 3, 1)  # seeds reaching one slab
    parts = []
    lo = 0
    while lo < n_lay:
        # the slab [lo, hi): the most layers whose reaching seeds (layers lo - w .. hi + w - 1)
        # stay within the budget, at least one
        top = int(np.searchsorted(first, first[max(lo - w, 0)] + budget, side="right")) - 1
        hi = n_lay if top >= n_lay else min(max(top - w, lo + 1), n_lay)
        sel = order[first[max(lo - w, 0)]:first[min(hi + w, n_lay)]]
        if len(sel):
            base = near[sel]
            cnt = np.empty((len(sel), 2 * w + 1), np.int64)
            args = (origin, float(h), dims, int(w), float(depth), float(min_depth))
            _oriented_counts(S, N, sel, *args, lo, hi, base, cnt)
            layer_n, pos = _layer_slots(base, cnt, int(w), lo, hi - lo)
            out = np.empty(layer_n[-1], np.int64)
            _oriented_emit(S, N, sel, *args, base, cnt, pos, out)
            del base, cnt, pos
            uniq = np.empty(hi - lo, np.int64)
            _dedupe_layers(out, layer_n, uniq, _DEBRUIJN_POS)
            start = np.zeros(hi - lo + 1, np.int64)
            np.cumsum(uniq, out=start[1:])
            res = np.empty(start[-1], np.int64)
            _gather_layers(out, layer_n, start, res)
            parts.append(res)
        lo = hi
    return np.concatenate(parts) if parts else np.empty(0, np.int64)


@njit(cache=True)
def decode(keys, origin, h):
    n = keys.shape[0]
    P = np.empty((n, 3))
    for i in range(n):
        k = keys[i]
        P[i, 0] = origin[0] + h * ((k >> (2 * KEY_BITS)) & KEY_MASK)
        P[i, 1] = origin[1] + h * ((k >> KEY_BITS) & KEY_MASK)
        P[i, 2] = origin[2] + h * (k & KEY_MASK)
    return P


class Voxelizer:
    """Nested lattices over a mesh's bounding box, with signed surface distances.

    Parameters
    ----------
    vertices, faces : arrays of a validated closed mesh.
    h0 : float
        Spacing of the coarsest (level 0) lattice.
    """

    def __init__(self, vertices, faces, h0: float):
        self.V = np.ascontiguousarray(vertices, dtype=np.float64)
        self.F = np.ascontiguousarray(faces, dtype=np.int64)
        self.bvh = BVH.of_triangles(self.V, self.F)
        # winding numbers beside the faces nothing crosses: their points need no ray cast
        crossed = crossed_faces(self.V, self.F, *self.bvh.arrays)
        self.crossed_faces = int(crossed.sum())
        self.side = face_sides(self.V, self.F, crossed, *self.bvh.arrays, RAY_DIRS)
        self.h0 = float(h0)
        lo = self.V.min(axis=0)
        self.origin = lo - 0.5 * self.h0
        self.points_evaluated = 0

    def spacing(self, level: int) -> float:
        return self.h0 / (1 << level)

    def dims(self, level: int) -> np.ndarray:
        hi = self.V.max(axis=0) + 0.5 * self.h0
        d = np.floor((hi - self.origin) / self.spacing(level)).astype(np.int64) + 1
        if (d >= (1 << KEY_BITS)).any():
            raise ValueError(
                f"lattice level {level} needs {d.max()} points per axis (limit {1 << KEY_BITS}): "
                "max_error is too small for this mesh's size; check units"
            )
        return d

    def signed_distance(self, P: np.ndarray) -> np.ndarray:
        """Signed distance (positive inside) of points ``P (n, 3)`` to the surface."""
        self.points_evaluated += len(P)
        if len(P) == 0:
            return np.empty(0)
        return signed_distance(np.ascontiguousarray(P), self.V, self.F, self.side, *self.bvh.arrays, RAY_DIRS)

    def level0(self):
        """All level-0 lattice points inside the mesh and their surface distance.

        The signed distance is 1-Lipschitz (its sign flips only across the surface), so a
        coarse lattice of LEVEL0_COARSE spacings first rules out the points that lie farther
        outside than their distance to its nearest point: most of the box around a jaw,
        whose far-away points need the longest nearest-triangle searches. The points left
        are evaluated as without the cull (same result, a fraction of the time).
        """
        d = self.dims(0)
        s = LEVEL0_COARSE
        ci = [np.arange(0, n + s, s) for n in d]  # coarse lattice, one step past the fine one
        cI, cJ, cK = np.meshgrid(*ci, indexing="ij")
        Q = self.origin + self.h0 * np.stack([cI.ravel(), cJ.ravel(), cK.ravel()], axis=1).astype(np.float64)
        DQ = self.signed_distance(Q).reshape(cI.shape)
        ii, jj, kk = np.meshgrid(np.arange(d[0]), np.arange(d[1]), np.arange(d[2]), indexing="ij")
        ii, jj, kk = ii.ravel(), jj.ravel(), kk.ravel()
        qi, qj, qk = (ii + s // 2) // s, (jj + s // 2) // s, (kk + s // 2) // s  # nearest coarse point
        off = self.h0 * np.sqrt((ii - s * qi) ** 2 + (jj - s * qj) ** 2 + (kk - s * qk) ** 2)
        maybe = DQ[qi, qj, qk] + off * (1.0 + 1e-9) + 1e-12 * self.h0 >= 0.0  # may be inside (or on) the surface
        P = self.origin + self.h0 * np.stack([ii[maybe], jj[maybe], kk[maybe]], axis=1).astype(np.float64)
        D = self.signed_distance(P)
        keep = D > 0
        return P[keep], D[keep]

    def band_keys(self, level: int, *groups, oriented=None) -> np.ndarray:
        """Sorted lattice keys of the level-``level`` points within a cube of some seed point.

        ``groups`` are ``(seeds (k, 3), half_width)`` pairs; the result is the union of the
        groups' bands (8 bytes a point: the caller decodes it in chunks, see ``decode``).
        ``oriented`` is one more group, ``(seeds, half_width, normals, depth, min_depth)``, of
        seeds ``depth`` behind the surface along the unit inward ``normals``: of each cube it
        keeps the points at least ``min_depth`` behind the seed's tangent plane, all of them
        where the normal is zero (see ``oriented_band``).
        """
        h = self.spacing(level)
        dims = self.dims(level)
        parts = []
        for seeds, half_width in groups:
            if len(seeds) == 0:
                continue
            w = int(np.ceil(half_width / h - 1e-9))
            keys = sorted_unique(_seed_keys(np.ascontiguousarray(seeds, dtype=np.float64), self.origin, h, dims))
            # separable cube dilation, kept sorted and unique after each axis: memory ~ (2w+1) x the band
            for axis in range(3):
                keys = _dilate(keys, axis, w, dims)
            parts.append(keys)
        if oriented is not None and len(oriented[0]):
            seeds, half_width, normals, depth, min_depth = oriented
            w = int(np.ceil(half_width / h - 1e-9))
            parts.append(oriented_band(seeds, normals, self.origin, h, dims, w, depth, min_depth))
        if not parts:
            return np.empty(0, np.int64)
        return parts[0] if len(parts) == 1 else sorted_unique(np.concatenate(parts))
