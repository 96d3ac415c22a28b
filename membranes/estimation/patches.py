"""Coloured patch problems: mixed RT_1 × DG1 systems on a distributed mesh, solved with dense
inverses shared by congruent patches (§5, §6, §12).

A *patch* is a group of cells; the patch problems of §5 (and of the multilevel flux, §6) are
mixed Raviart–Thomas problems on each patch:

    (σ, τ) - (γ, ∇·τ) - (∇·σ, q) = ℓ(τ, q)     ∀ (τ, q) ∈ V^p × Q^p,

V^p = RT_1 on the patch's cells with zero normal flux on the patch boundary (except on ∂Ω for a
patch that is not *interior*), Q^p = DG1 on its cells (zero mean on an interior patch). The
divergence equation is negated against §5 so that the matrix is symmetric.

**Groups.** Patches straddle processes, and dolfinx 0.5.2 cannot ghost vertex patches. So the
patches are handed over in *groups* (colours) whose patches share no cell. Every dof kept for a
group is supported on the cells of one patch (a facet dof is kept only if both its cells are in
that patch, or its one cell if the facet lies on ∂Ω), so the entry of the matrix A of the form
above, assembled by dolfinx over the whole mesh (forms.equilibration.patch_system), between two
kept dofs is the sum of the cell blocks of that patch only: each patch's matrix is a principal
submatrix A_p of A. Each patch is solved on one process, its *home*. A VecScatter per group
moves right-hand sides from the dofs' owners to the homes and solutions back (in the set-up, a
*route* of one MPI Alltoallv each way, `_to_home`/`_to_owners`, does the same before the home
layout is known); PETSc's MatCreateSubMatrices brings the rows of the blocks that are needed to
the homes (as for overlapping Schwarz subdomains).

**Shared dense inverses.** The blocks are taken in the canonical basis of `congruence`, where
the blocks of translated patches are equal to round-off. Patches with equal translation
invariant keys (`congruence.patch_keys`) are candidates for one class; only the block of the
first patch of a new key is taken from A. Every patch of a group is then checked against its
class's block at once, by one product of A with a random probe (`_probe`; the patches of a
group share no cell), and a patch that fails gets its own block and class. Each class keeps one
dense inverse (LAPACK). The home vector holds the patches class by class, so that a call
solves all patches of a class by one matrix product. Where nothing is congruent (an
unstructured mesh) every patch has its own block and inverse.

**Zero mean on interior patches.** Instead of a Lagrange multiplier, one DG dof k of the patch
(its first in the canonical order) is removed, both as unknown (γ_k = 0) and as equation (the
row of its basis function φ_k). The reduced system is nonsingular: with B the divergence block,
B maps the zero-flux RT space onto {b : Σ_i b_i = 0} (div is onto the zero-mean DG1 functions and
Σ_i φ_i = 1), so Bᵀγ = 0 only for γ constant, which γ_k = 0 excludes, and σ = 0 follows from the
first row as usual. The removed row is implied when the data are compatible, (ℓ_q, 1) = 0: then
(∇·σ, φ_k) = (∇·σ, 1) - Σ_{i≠k} (∇·σ, φ_i) = 0 - Σ_{i≠k} ℓ_i = ℓ_k. So σ is the solution of §5
and γ differs from the zero-mean one by a constant. With incompatible data the defect would
land on the pinned dof's cell; §4's lifting makes the vertex patches of §5 compatible, and the
multilevel data of §6 are compatible by construction.

Only facet-cell connectivity and index-map communication are used, so the engine works on
GhostMode.none meshes (the patch id of the cell across a process boundary travels with the
facet's index map) as well as on ghosted ones (only owned cells carry patch ids).
"""

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

import forms.equilibration as equilibration_forms

from .congruence import (
    DG,
    INTERIOR,
    NEGATIVE,
    ROUNDING,
    SAME,
    BasisChange,
    Blocks,
    _kind,
    _pairs,
    canonical_block,
    canonical_dofs,
    patch_keys,
    to_canonical,
)
from .exchange import Shared, alltoallv, colour_vertices, reduce_by_key

__all__ = ["PatchSystems", "Shared", "alltoallv", "colour_vertices", "mixed_space",
           "reduce_by_key"]

CHUNK = 1 << 18          # rows of patch blocks taken from A at a time (bounds the set-up memory)


def mixed_space(mesh):
    """RT_1 × DG1 (basix "RT" degree 2, "DG" degree 1) as one dolfinx mixed space."""
    from dolfinx import fem
    cell = mesh.ufl_cell()
    element = ufl.MixedElement(ufl.FiniteElement("RT", cell, 2), ufl.FiniteElement("DG", cell, 1))
    return fem.FunctionSpace(mesh, element)


def stable_order(keys):
    """np.argsort(keys, kind="stable") for non-negative integers, by passes over 16 bits
    (numpy's stable sort of uint16 is a radix sort: linear time)."""
    order, shift, top = None, 0, int(keys.max(initial=0))
    while True:
        digit = ((keys if order is None else keys[order]) >> shift).astype(np.uint16)
        step = np.argsort(digit, kind="stable")
        order = step if order is None else order[step]
        shift += 16
        if top >> shift == 0:
            return order


# ## The coloured patch systems

class PatchSystems:
    """The patch problems of one mesh in groups, set up once (see the module docstring).

    `patches[c]`: int array over the owned cells, the global id of the patch of group (colour)
    c containing the cell, or -1; no two patches of one group share a cell. `interior[c]`: bool
    array over the owned cells, True where the cell's patch is interior (zero normal flux on all
    its boundary and zero mean; otherwise its facets on ∂Ω are free). Patch ids must be unique
    within a group across processes; a patch's cells may live on several processes. `share`:
    congruent patches share one inverse (False: every patch has its own). `rhs="divergence"`:
    right-hand sides vanish on the RT dofs (only DG moments, as in §6); `solution="flux"`: only
    the RT part of the solutions is wanted (σ; γ is returned as zero). Each class then keeps
    only the block of its inverse between those dofs.

    Each patch is solved on one process, its *home*: the owner of its cell of least global
    index. The kept dofs of all patches at home on a process form its *home vector* (numpy),
    class by class. A call goes: `home = home_vector()`; `gather(c, b, home)` for each group c
    (b a PETSc Vec on W with final owned entries, the right-hand side of group c's patches);
    `x = solve_home(home, extra)` (extra: canonical home values to add, see `canonical`); then
    `scatter(c, x, out, add)` puts group c's solutions into a W Vec (zero elsewhere unless
    `add`), and `add_flux(out, sigma)` adds its RT part to an RT_1 Function. `solve(c, b, out,
    extra)` does all this for one group.
    """

    def __init__(self, mesh, patches, interior, W=None, share=True, rhs="full",
                 solution="full"):
        from dolfinx import fem
        from dolfinx.fem.petsc import assemble_matrix
        if rhs not in ("full", "divergence") or solution not in ("full", "flux"):
            raise ValueError(f"rhs must be 'full' or 'divergence', solution 'full' or 'flux'; "
                             f"got {rhs!r}, {solution!r}")
        self.rhs, self.solution = rhs, solution
        self.mesh, self.comm = mesh, mesh.comm
        self.W = W = W if W is not None else mixed_space(mesh)
        self.rt_space, rt_map = W.sub(0).collapse()
        self.rt_map = np.asarray(rt_map, dtype=np.int64)
        self.ngroups = len(patches)
        self._topology(mesh, W)
        self.position, self.entity, self.code, self.blocks, self.disagree = canonical_dofs(
            mesh, W, self.c2f, self.rt_dofs, self.dg_dofs)
        n = self.nowned
        # canonical order in a patch: its RT facet dofs, its interior RT dofs (a cell's two
        # adjacent), its DG dofs, each by position
        self.by_rank = np.lexsort((self.entity[:n], self.position[:n, 0],
                                   _kind(self.code[:n])))
        rank = np.full(self.nlocal, n, dtype=np.int32)            # ghost dofs: n
        rank[self.by_rank] = np.arange(n, dtype=np.int32)
        self.facet_rank, self.cell_rank = rank[self.facet_dofs], rank[self.cell_dofs]
        del rank, self.facet_dofs, self.cell_dofs

        # A over the whole mesh, once; each group's rows at home are taken from it, made
        # canonical and classified, one group at a time
        (sigma, gamma), (tau, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
        A = assemble_matrix(fem.form(equilibration_forms.patch_system(sigma, gamma, tau, q)))
        A.assemble()
        signs = A.createVecLeft()
        signs.array[:] = np.where(self.code[:n] & NEGATIVE, -1.0, 1.0)
        A.diagonalScale(signs, signs)                 # the ±1 of G on facet dofs
        signs.destroy()
        classes, self.known = Blocks(), (np.zeros(0, dtype=np.uint64), np.zeros(0, np.int64))
        self.rejected, self.worst = 0, 0.0
        groups, vecs = [], A.createVecs()
        for pid, inner in zip(patches, interior):
            dofs, offsets, code, tolerance, nsigma, key, route = self._home_dofs(
                np.asarray(pid, dtype=np.int64), np.asarray(inner, dtype=bool))
            npatch = len(offsets) - 1
            if share:
                cls = self._lookup(key)
                new = np.flatnonzero(cls < 0)
                new = new[np.unique(key[new], return_index=True)[1]]     # one per new key
                self._remember(key[new], self._extract(A, dofs, offsets, code, nsigma, new,
                                                       classes))
                cls = self._lookup(key)
            else:
                cls = self._extract(A, dofs, offsets, code, nsigma, np.arange(npatch), classes)
            error, ref = self._probe(A, vecs, route, offsets, code, cls, classes)
            ok = error <= tolerance * ref
            bad = np.flatnonzero(~ok)
            if self.comm.allreduce(bad.size, op=MPI.SUM):
                cls[bad] = self._extract(A, dofs, offsets, code, nsigma, bad, classes)
            self.rejected += bad.size
            if np.any(ok):
                self.worst = max(self.worst, float((error[ok] / ref[ok]).max()))
            del route
            groups.append((dofs.astype(PETSc.IntType), offsets, code.astype(np.int16), cls))
        A.destroy()
        for v in vecs:
            v.destroy()
        self._layout(groups, classes)
        # only the home layout, the scatters and the inverses are kept
        for name in ("position", "entity", "code", "by_rank", "c2f", "facet_shared",
                     "facet_owned_cells", "facet_cells", "cell_global", "cell_h", "rt_dofs",
                     "dg_dofs", "facet_rank", "cell_rank", "known"):
            delattr(self, name)

    def _lookup(self, key):
        """The classes of the keys (-1: not seen yet on this process)."""
        keys, cls = self.known
        at = np.minimum(np.searchsorted(keys, key), max(keys.size - 1, 0))
        return np.where(keys[at] == key, cls[at], -1) if keys.size else np.full(key.size, -1)

    def _remember(self, key, cls):
        keys = np.concatenate([self.known[0], key])
        order = np.argsort(keys, kind="stable")
        self.known = keys[order], np.concatenate([self.known[1], cls])[order]

    def _extract(self, A, dofs, offsets, code, nsigma, which, classes):
        """New classes for the blocks of the patches `which` of a group, taken from A (rows
        and columns at the patches' kept dofs, a chunk at a time: collective) and made
        canonical."""
        which = np.asarray(which, dtype=np.int64)
        n = offsets[which + 1] - offsets[which]
        sub = np.concatenate([[0], np.cumsum(n)]).astype(np.int64)
        rows = np.repeat(offsets[which] - sub[:-1], n) + np.arange(sub[-1])
        out = np.zeros(which.size, dtype=np.int64)
        for first, last in self._chunks(sub):
            r = rows[sub[first]:sub[last]]
            iset = PETSc.IS().createGeneral(dofs[r].astype(PETSc.IntType), comm=PETSc.COMM_SELF)
            block = A.createSubMatrices(iset)[0]
            iset.destroy()
            ia, ja, a = block.getValuesCSR()
            block.destroy()
            ia, ja = ia.astype(np.int64), ja.astype(np.int64)
            a = canonical_block(ia, ja, a, code[r], self.blocks)
            out[first:last] = classes.add(ia, ja, a, sub[first:last + 1] - sub[first],
                                          nsigma[which[first:last]])
        return out

    def _probe(self, A, vecs, route, offsets, code, cls, classes):
        """(error, ref) per patch of a group: max_i |(Ã_p v - u)_i| for its class's probe v and
        u = Ã_class v, all patches of the group at once through one product with A (the
        patches share no cell), and the class's reference magnitude (see `congruence`).
        Collective."""
        v, u, start, size, _, ref = classes.probes()
        n = np.diff(offsets)
        mismatch = size[cls] != n if cls.size else np.zeros(0, dtype=bool)
        cls_ok = np.where(mismatch, 0, cls)
        at = np.repeat(start[cls_ok] - offsets[:-1], n) + np.arange(offsets[-1])
        at[np.repeat(mismatch, n)] = 0
        pairs = _pairs(code)
        # A carries the signs of G already: only its interior blocks act here
        w = to_canonical(v[at], 1.0, pairs, self.blocks, transpose=False)
        x, y = vecs
        x.set(0.0)
        self._to_owners(route, w, x.array, add=False)
        A.mult(x, y)
        got = self._to_home(route, y.array_r, np.empty(offsets[-1]))
        got = to_canonical(got, 1.0, pairs, self.blocks, transpose=True)
        diff = np.abs(got - u[at])
        error = np.maximum.reduceat(diff, offsets[:-1]) if n.size else diff[:0]
        error[mismatch] = np.inf
        return error, ref[cls_ok]

    def _to_home(self, route, values, home):
        """home[dest] ← values[send] (owned W entries) through the route of a group."""
        send, sc, rc, dest = route
        home[dest] = alltoallv(self.comm, values[send], sc, rc)
        return home

    def _to_owners(self, route, home, values, add):
        """values[send] ← (or +=) home[dest]: the reverse of `_to_home`."""
        send, sc, rc, dest = route
        got = alltoallv(self.comm, home[dest], rc, sc)
        if add:
            values[send] += got
        else:
            values[send] = got
        return values

    def _chunks(self, offsets):
        """Ranges of patches (first, last) of about CHUNK rows, as many on every process
        (MatCreateSubMatrices is collective): the blocks are taken a chunk at a time."""
        npatch = len(offsets) - 1
        count = self.comm.allreduce(max(1, -(-int(offsets[-1]) // CHUNK)), op=MPI.MAX)
        bounds = np.searchsorted(offsets, np.linspace(0, offsets[-1], count + 1)[1:-1])
        bounds = np.concatenate([[0], np.minimum(bounds, npatch), [npatch]])
        return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))

    def _topology(self, mesh, W):
        """Cell → facet and cell → dof tables (all local cells), facet cell counts (global)."""
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim, tdim - 1)
        mesh.topology.create_connectivity(tdim - 1, tdim)
        cmap = mesh.topology.index_map(tdim)
        self.ncells = cmap.size_local
        nall = cmap.size_local + cmap.num_ghosts
        self.cell_global = np.asarray(cmap.local_to_global(np.arange(self.ncells, dtype=np.int32)),
                                      dtype=np.int64)
        self.c2f = mesh.topology.connectivity(tdim, tdim - 1).array.reshape(nall, 3)
        fmap = mesh.topology.index_map(tdim - 1)
        self.nfacets = fmap.size_local + fmap.num_ghosts
        self.facet_shared = Shared(fmap, self.comm)
        # the (at most two) owned cells of each local facet (-1: none), and the number of cells
        # of each facet over the whole mesh (owned cells only, each counted by its owner)
        facets = self.c2f[:self.ncells].ravel()
        order = stable_order(facets)
        count = np.bincount(facets, minlength=self.nfacets)
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        self.facet_owned_cells = np.full((self.nfacets, 2), -1, dtype=np.int64)
        has = count > 0
        self.facet_owned_cells[has, 0] = order[start[has]] // 3
        two = count > 1
        self.facet_owned_cells[two, 1] = order[start[two] + 1] // 3
        self.facet_cells = self.facet_shared.forward(self.facet_shared.reverse(count, np.add))

        rt = W.sub(0).element.basix_element.entity_dofs
        self.rt_dofs = W.sub(0).dofmap.list.array.reshape(nall, -1)
        self.dg_dofs = W.sub(1).dofmap.list.array.reshape(nall, -1)
        # the RT dofs of each local facet, and the interior RT and DG dofs of each local cell
        self.facet_dofs = np.zeros((self.nfacets, len(rt[tdim - 1][0])), dtype=np.int32)
        for i, cols in enumerate(rt[tdim - 1]):
            self.facet_dofs[self.c2f[:, i]] = self.rt_dofs[:, cols]
        self.cell_dofs = np.hstack([self.rt_dofs[:, rt[tdim][0]], self.dg_dofs])
        # the shortest edge of each owned cell, and the largest |x| of the mesh (§12: the
        # tolerance of the block comparisons)
        nodes = mesh.geometry.dofmap.array.reshape(-1, 3)[:self.ncells]
        x = mesh.geometry.x[:, :2][nodes]
        self.cell_h = np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2).min(axis=1)
        self.radius = self.comm.allreduce(float(np.abs(mesh.geometry.x).max(initial=0.0)),
                                          op=MPI.MAX)
        imap = W.dofmap.index_map
        self.nowned = imap.size_local
        self.nlocal = imap.size_local + imap.num_ghosts
        self.rstart = imap.local_range[0]

    def _home_dofs(self, pid, inner):
        """The kept W dofs of the group's patches at home on this process (global indices), in
        canonical order patch by patch (RT facet dofs, interior RT dofs, DG dofs), the patches'
        offsets, the dofs' codes, the patches' tolerances, numbers of RT dofs and keys, and the
        group's route (see `_to_home`). A collective call: every process hands over its owned
        kept dofs."""
        comm = self.comm
        # per facet, over its (at most two) cells: the largest and smallest patch id + 1
        # (0 = no patch), and whether a cell's patch is not interior; reduced across processes
        least = np.iinfo(np.int64).min
        cell_info = np.stack([pid + 1, -(pid + 1), ((pid >= 0) & ~inner)], axis=1)
        cell_info = np.vstack([cell_info, np.full((1, 3), least)])     # row -1: no cell
        info = np.maximum(cell_info[self.facet_owned_cells[:, 0]],
                          cell_info[self.facet_owned_cells[:, 1]])
        self.facet_shared.forward(self.facet_shared.reverse(info, np.maximum))
        hi, lo, free = info[:, 0], -info[:, 1], info[:, 2]
        inside = (self.facet_cells == 2) & (hi == lo) & (hi > 0)
        on_boundary = (self.facet_cells == 1) & (free == 1)
        facet_patch = np.where(inside | on_boundary, hi - 1, -1)

        # the patch of every local dof the group keeps (-1: not kept)
        # (by rank in the canonical order of the owned dofs; ghost dofs share the last entry)
        patch = np.full(self.nowned + 1, -1, dtype=np.int64)
        patch[self.facet_rank] = facet_patch[:, None]
        cells = np.flatnonzero(pid >= 0)
        patch[self.cell_rank[cells]] = pid[cells, None]
        # the owned kept dofs in canonical order, patch by patch
        ranked = np.flatnonzero(patch[:-1] >= 0)
        kept, kp = self.by_rank[ranked], patch[ranked]
        del patch, ranked
        by_patch = stable_order(kp)
        kept, kp = kept[by_patch], kp[by_patch]
        del by_patch

        # home of each patch: the owner of its cell of least global index, found with the
        # patch's interior flag in one distributed reduction over the patches seen here
        # (and its shortest edge)
        by_cell = cells[stable_order(pid[cells])]
        new = np.flatnonzero(np.diff(pid[by_cell], prepend=-1))
        keys = pid[by_cell[new]]
        values = ((self.cell_global[by_cell] * comm.size + comm.rank) << 1) | ~inner[by_cell]
        values = np.minimum.reduceat(values, new) if new.size else values[:0]
        h = np.minimum.reduceat(self.cell_h[by_cell], new) if new.size else np.zeros(0)
        new = np.flatnonzero(np.diff(kp, prepend=-1))
        seen = kp[new]                                              # unique, sorted
        extra = seen[keys[np.minimum(np.searchsorted(keys, seen), keys.size - 1)] != seen] \
            if keys.size else seen                      # patches with no owned cell here
        if extra.size:
            keys = np.concatenate([keys, extra])
            values = np.concatenate([values, np.full(extra.size, np.iinfo(np.int64).max)])
            h = np.concatenate([h, np.full(extra.size, np.inf)])
            order = np.argsort(keys)
            keys, values, h = keys[order], values[order], h[order]
        at = np.searchsorted(keys, seen)
        count = np.diff(np.append(new, kp.size))
        first = np.repeat(reduce_by_key(comm, keys, values, np.minimum)[at], count)
        h = np.repeat(reduce_by_key(comm, keys, h, np.minimum)[at], count)
        home = (first >> 1) % comm.size
        code = self.code[kept] | np.where(first & 1, np.int16(0), np.int16(INTERIOR))

        # send every kept dof to its patch's home (in order), which keeps the patches whole;
        # column by column (no copies on one process)
        order = stable_order(home) if comm.size > 1 else slice(None)
        send = np.bincount(home, minlength=comm.size).astype(np.int64)
        recv = np.asarray(comm.alltoall(send.tolist()), dtype=np.int64)
        kept, home = kept[order], home[order]

        def move(column):
            return alltoallv(comm, column, send, recv)

        gdof, gpatch, gcode = move(kept + self.rstart), move(kp[order]), move(code[order])
        gpoint, gh = move(self.position[kept]), move(h[order])
        del kp, code, h, first, at
        received = gdof.size
        perm = None                  # received → canonical order, patch by patch (None: same)
        if comm.size > 1:
            entity = move(self.entity[kept])
            perm = stable_order(gpatch)
            # a patch with dofs from several processes: merge them in canonical order
            source = np.repeat(np.arange(comm.size), recv)[perm]
            new = np.flatnonzero(np.diff(gpatch[perm], prepend=-1) != 0)
            mixed = (np.minimum.reduceat(source, new) != np.maximum.reduceat(source, new)
                     if new.size else np.zeros(0, dtype=bool))
            redo = np.flatnonzero(np.repeat(mixed, np.diff(np.append(new, received))))
            if redo.size:
                r = perm[redo]
                perm[redo] = r[np.lexsort((entity[r], gpoint[r, 0], _kind(gcode[r]),
                                           gpatch[r]))]
        patch = gpatch if perm is None else gpatch[perm]
        code = gcode if perm is None else gcode[perm]
        # patch offsets; interior patches lose their first DG dof
        new = np.flatnonzero(np.diff(patch, prepend=-1) != 0)
        dg = np.flatnonzero(_kind(code) == DG)
        pinned = dg[np.flatnonzero(np.diff(patch[dg], prepend=-1) != 0)]
        pinned = pinned[(code[pinned] & INTERIOR) != 0]
        bounds = np.append(new, received)
        start = bounds - np.searchsorted(pinned, bounds)
        keep = np.ones(received, dtype=bool)
        keep[pinned] = False
        sel = np.flatnonzero(keep) if perm is None else perm[keep]      # received indices
        h = gh[new] if perm is None else gh[perm[new]]
        tolerance = np.maximum(SAME, ROUNDING * np.finfo(float).eps * self.radius / h)
        # the route: each received dof's place at home; the owners forget the pinned dofs
        dest = np.full(received, -1, dtype=np.int64)
        dest[sel] = np.arange(sel.size)
        sent_kept = alltoallv(comm, dest >= 0, recv, send)
        source = np.repeat(np.arange(comm.size), recv)
        route = (kept[sent_kept].astype(np.int32),
                 np.bincount(home[sent_kept], minlength=comm.size).astype(np.int64),
                 np.bincount(source[dest >= 0], minlength=comm.size).astype(np.int64),
                 dest[dest >= 0].astype(np.int32))
        dofs, code = gdof[sel], code[keep]
        nsigma = np.add.reduceat(_kind(code) != DG, start[:-1]) if code.size else start[:0]
        key = patch_keys(start, code, gpoint, h, sel)
        return dofs, start, code, tolerance, nsigma, key, route

    def _layout(self, groups, classes):
        """Home order (size, class multiplicity, class, group, patch), the routes to it, the
        canonical change of basis in home order, and the inverses of the classes."""
        comm = self.comm
        n = np.concatenate([np.diff(g[1]) for g in groups])
        cls = np.concatenate([g[3] for g in groups])
        group = np.concatenate([np.full(len(g[1]) - 1, c) for c, g in enumerate(groups)])
        nclasses = classes.count()
        count = np.bincount(cls, minlength=nclasses)
        rt = np.array([classes.shape(k)[2] for k in range(nclasses)], dtype=np.int64)
        order = np.lexsort((np.arange(cls.size), group, cls, count[cls], rt[cls], n))
        start = np.zeros(cls.size, dtype=np.int64)
        start[order] = np.cumsum(n[order]) - n[order]
        self.home_size = int(n.sum())
        code = np.zeros(self.home_size, dtype=np.int16)
        # per group a VecScatter from the owners to the home positions: one pass per call
        template = PETSc.Vec().createMPI((self.nowned, PETSc.DECIDE), comm=comm)
        hv = PETSc.Vec().createWithArray(self.home_vector(), comm=PETSc.COMM_SELF)
        self.scatters, self.group_sizes = [], []
        first = 0
        for dofs, offsets, gcode, _ in groups:
            k = np.diff(offsets)
            at = (np.repeat(start[first:first + k.size] - offsets[:-1], k)
                  + np.arange(offsets[-1]))
            first += k.size
            code[at] = gcode
            by_home = np.argsort(at)                  # in home order: a cheaper set-up
            src = PETSc.IS().createGeneral(dofs[by_home], comm=PETSc.COMM_SELF)
            dst = PETSc.IS().createGeneral(at[by_home].astype(PETSc.IntType),
                                           comm=PETSc.COMM_SELF)
            self.scatters.append(PETSc.Scatter().create(template, src, hv, dst))
            src.destroy()
            dst.destroy()
            self.group_sizes.append(comm.allreduce(int(offsets[-1]), op=MPI.SUM))
        template.destroy()
        hv.destroy()
        self.change = BasisChange(code, np.append(start[order], self.home_size), self.blocks)
        del code

        # per class the block of its inverse from the right-hand side entries used to the
        # solution entries wanted (RT dofs first, DG dofs last in a patch); one product per
        # (shape, count) for all the patches of its classes
        self.solves = []
        shape = np.array([classes.shape(k) for k in range(nclasses)], dtype=np.int64)
        shape = shape.reshape(-1, 3)
        ok = True
        try:
            first = np.full(nclasses, np.iinfo(np.int64).max)
            np.minimum.at(first, cls, start)                  # each class's first patch
            used = np.flatnonzero(count > 0)              # (n, n_σ, count, class) by rows
            ranked = np.stack([shape[used, 0], shape[used, 2], count[used], used], axis=1)
            ranked = ranked[np.lexsort(ranked.T[::-1])]
            for size, rt in np.unique(ranked[:, :2], axis=0).tolist():
                these = ranked[(ranked[:, 0] == size) & (ranked[:, 1] == rt)]
                inputs = slice(rt if self.rhs == "divergence" else 0, size)
                outputs = slice(0, rt if self.solution == "flux" else size)
                operators = classes.operators(these[:, 3], inputs, outputs)
                at = 0
                for m in np.unique(these[:, 2]):
                    K = int(np.count_nonzero(these[:, 2] == m))
                    self.solves.append((int(first[these[at, 3]]), K, int(m), size, inputs,
                                        outputs, operators[at:at + K].transpose(0, 2, 1)))
                    at += K
        except np.linalg.LinAlgError:
            ok = False
        if not comm.allreduce(ok, op=MPI.LAND):
            raise RuntimeError("a patch problem is singular")
        if ok and sum(s[1] * s[2] * s[3] for s in self.solves) != self.home_size:
            raise RuntimeError("the products do not cover the home vector")
        self.nclasses, self.npatches = nclasses, cls.size
        classes.release()

    def home_vector(self):
        """A zero home vector (numpy): the kept dofs of the patches at home, all groups."""
        return np.zeros(self.home_size)

    def _vec(self, array):
        return PETSc.Vec().createWithArray(array, comm=PETSc.COMM_SELF)

    def gather(self, c, b, home):
        """home ← the entries of the W vector b at group c's kept dofs (dolfinx's basis)."""
        hv = self._vec(home)
        self.scatters[c].scatter(b, hv, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        hv.destroy()
        return home

    def canonical(self, home):
        """Gᵀ home in place: gathered right-hand sides in the canonical basis. With
        rhs="divergence" the right-hand sides vanish on the RT dofs, where alone G differs from
        the identity: nothing to do."""
        if self.rhs == "divergence":
            return home
        return self.change.apply(home, transpose=True)

    def solve_home(self, home, extra=None):
        """The solutions of all patches for the gathered right-hand sides `home` (overwritten)
        plus `extra` (canonical, e.g. `canonical(gathered)` of a fixed part), as a home vector
        in dolfinx's basis."""
        rhs = self.canonical(home)
        if extra is not None:
            rhs += extra
        x = np.zeros_like(rhs)
        for h0, K, m, n, inputs, outputs, operator_t in self.solves:
            h1 = h0 + K * m * n
            np.matmul(rhs[h0:h1].reshape(K, m, n)[:, :, inputs], operator_t,
                      out=x[h0:h1].reshape(K, m, n)[:, :, outputs])
        return self.change.apply(x, transpose=False)

    def scatter(self, c, x, out, add=False):
        """The solutions of group c (home vector x) into the W vector `out` (owned entries):
        added, or written with zeros at the dofs the group does not keep."""
        if not add:
            out.set(0.0)
        xv = self._vec(x)
        self.scatters[c].scatter(xv, out, PETSc.InsertMode.ADD if add else
                                 PETSc.InsertMode.INSERT, PETSc.ScatterMode.REVERSE)
        xv.destroy()
        return out

    def solve(self, c, b, out=None, extra=None):
        """Solve group c for the W vector `b` (+ `extra`, canonical home values); the W vector
        `out` holds the solution at the kept dofs and zero elsewhere (owned entries)."""
        if out is None:
            out = b.duplicate()
        home = self.gather(c, b, self.home_vector())
        return self.scatter(c, self.solve_home(home, extra), out)

    def add_flux(self, x, sigma):
        """sigma.x (owned part) += the RT part of the W vector x (owned part)."""
        n = self.rt_space.dofmap.index_map.size_local
        sigma.x.array[:n] += x.array_r[self.rt_map[:n]]

    def sizes(self):
        """Global number of unknowns of each group's patches."""
        return list(self.group_sizes)

    def stats(self):
        """Global facts of the sharing: patches, classes (distinct inverses, summed over the
        processes), patches rejected by the probe of their key's class (they have their own
        block), inverse memory in bytes, facet dofs whose two cells disagree on the canonical
        basis (0), and the largest probe residual of an accepted patch relative to its class's
        reference magnitude (within the tolerance, see `congruence`)."""
        memory = sum(s[6].nbytes for s in self.solves)
        local = np.array([self.npatches, self.nclasses, self.rejected, memory, self.disagree])
        total = self.comm.allreduce(local, op=MPI.SUM)
        out = dict(zip(("patches", "classes", "rejected", "inverse_bytes", "disagree"),
                       total.tolist()))
        out["worst"] = self.comm.allreduce(self.worst, op=MPI.MAX)
        return out

    def destroy(self):
        for s in self.scatters:
            s.destroy()
        self.scatters, self.solves = [], []
