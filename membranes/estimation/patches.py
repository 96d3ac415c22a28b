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
submatrix A_p of A, and equally of A assembled on any set of cells containing the patch's,
with rows and columns for the kept dofs only (`homes.assemble_rows`: per group, only the cells
of the patches whose blocks are taken are assembled, into rows numbered at those patches'
homes, so no matrix over the whole mesh is ever made and each home owns its blocks' rows).
Each patch is solved on one process, its *home*. Per group, index lists move the
right-hand sides of the dofs owned by a home's process to it and the solutions back
(VecGetValues / VecSetValues on a sequential Vec over the process's own entries), and a
VecScatter moves those of the others (none on one process).

**Shared dense inverses.** The blocks are taken in the canonical basis of `congruence`, where
the blocks of translated patches are equal to round-off. Patches with equal translation
invariant keys (`congruence.patch_keys`) form one class; only the block of the first patch of
a new key is taken, from A assembled on the cells of those patches of its group (their homes
mark them for the owners of their cells, `_marked_cells`). A patch whose size differs from its
key's class (a key collision) gets a class and block of its own. Each class keeps one dense
inverse (LAPACK). A group's home vector holds its patches class by class, so that a call
solves all the group's patches of a class by one matrix product; the groups are solved one
after the other, so that the home vector needs room for one group only. Where nothing is
congruent (an unstructured mesh) every patch has its own block and inverse. A patch solved
with its class's inverse has its own divergence rows (`congruence`); the users of the engine
check the divergence identity of every flux they make (`divergence`).

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

from .classes import ClassStore
from .congruence import (
    FACET,
    NEGATIVE,
    BasisChange,
    _kind,
    canonical_block,
    canonical_dofs,
)
from .exchange import (
    Shared,
    alltoallv,
    colour_vertices,
    ranges,
    reduce_by_key,
    run_starts,
    stable_order,
)
from .homes import HomeSetup, assemble_rows

SOLVE_CHUNK = 1 << 20     # home entries per product in `solve_home`
OPERATOR_CHUNK = 1 << 18  # entries of the inverses taken by index per product (`solve_home`)
RUN = 256                 # home entries of a run the routes copy as one slice (`_own_route`)

__all__ = ["PatchSystems", "Shared", "alltoallv", "colour_vertices", "mixed_space", "stable_order",
           "reduce_by_key"]


def mixed_space(mesh):
    """RT_1 × DG1 (basix "RT" degree 2, "DG" degree 1) as one dolfinx mixed space."""
    from dolfinx import fem
    cell = mesh.ufl_cell()
    element = ufl.MixedElement(ufl.FiniteElement("RT", cell, 2), ufl.FiniteElement("DG", cell, 1))
    return fem.FunctionSpace(mesh, element)


# ## The coloured patch systems

def local_vec(array):
    """A sequential PETSc Vec over the numpy array `array` (no copy): PETSc's indexed gets, sets
    and adds (VecGetValues, VecSetValues) and scatters on a process's own entries."""
    return PETSc.Vec().createWithArray(array, comm=PETSc.COMM_SELF)


class PatchSystems(HomeSetup):
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
    index. The kept dofs of one group's patches at home on a process form its *home vector*
    (numpy), class by class; one buffer (`home_vector`, the size of the largest group) serves
    every group in turn. A call goes, for each group c: `gather(c, b, home)` (b a PETSc Vec on
    W with final owned entries, the right-hand side of group c's patches); `x =
    solve_home(c, home)`; then `scatter(c, x, out, add)` puts group c's solutions into a W Vec
    (zero elsewhere unless `add`, which sums the groups), and `add_flux(out, sigma)` adds its
    RT part to an RT_1 Function. `solve(c, b, out)` does the first three for one group.
    """

    def __init__(self, mesh, patches, interior, W=None, share=True, rhs="full",
                 solution="full", store=None):
        if rhs not in ("full", "divergence") or solution not in ("full", "flux"):
            raise ValueError(f"rhs must be 'full' or 'divergence', solution 'full' or 'flux'; "
                             f"got {rhs!r}, {solution!r}")
        if store is not None and (not share or (store.rhs, store.solution) != (rhs, solution)):
            raise ValueError("a shared ClassStore needs share=True and the store's rhs and "
                             "solution")
        self.store = store if store is not None else ClassStore(rhs, solution)
        self.rhs, self.solution = rhs, solution
        self.mesh, self.comm = mesh, mesh.comm
        self.W = W = W if W is not None else mixed_space(mesh)
        # RT_1 as a space of its own, and the W dof of each of its dofs, read off the cells'
        # dofs (a space made anew: W.sub(0).collapse() is slower and gives its map as a
        # Python list)
        from dolfinx import fem
        rt, dg = W.sub(0), W.sub(1)            # (each W.sub builds a dofmap: made once)
        self.rt_space = fem.FunctionSpace(mesh, W.ufl_element().sub_elements()[0])
        imap = self.rt_space.dofmap.index_map
        self.rt_map = np.empty(imap.size_local + imap.num_ghosts, dtype=np.int32)     # local W dofs
        self.rt_map[self.rt_space.dofmap.list.array] = rt.dofmap.list.array
        self.ngroups = len(patches)
        self._topology(mesh, W, rt, dg)
        self.code, self.blocks, self.disagree, facet_point, cell_point = canonical_dofs(
            mesh, W, self.c2f, self.rt_dofs, self.dg_dofs, rt.element.basix_element,
            dg.element.basix_element, self.cell_xy)
        del rt, dg, self.cell_xy
        self._canonical_order(facet_point, cell_point)
        del facet_point, cell_point

        # per group its patches at home, their classes, and the patches whose blocks are
        # needed (`ClassStore.assign`, in the order `_extract` makes them)
        store = self.store
        self.collisions = 0
        pending = []
        for pid, inner in zip(patches, interior):
            dofs, offsets, code, nsigma, key, ids, owned = self._home_dofs(
                np.asarray(pid, dtype=np.int64), np.asarray(inner, dtype=bool))
            cls, new, collisions = store.assign(
                key, np.stack([np.diff(offsets), nsigma], axis=1), share)
            self.collisions += collisions
            pending.append([dofs, offsets, code, nsigma, ids, new, cls, owned])
        # per group A on the cells of those patches only; their blocks, made canonical
        marked = self._marked_cells([p.pop() for p in pending], [p[4][p[5]] for p in pending])
        for (dofs, offsets, code, nsigma, _, new, cls), cells in zip(pending, marked):
            if not np.array_equal(self._extract(cells, dofs, offsets, code, nsigma, new, store),
                                  cls[new]):
                raise RuntimeError("the classes were not made in the expected order")
        del marked
        # only the home layout, the scatters and the inverses are kept: the set-up's tables
        # go before the layout is made, and each group's dofs are narrowed one group at a
        # time (the set-up's peak memory is in `_layout`)
        for name in ("code", "c2f", "facet_shared", "facet_owned_cells", "facet_two",
                     "facet_one", "cell_global", "cell_h", "rt_dofs", "dg_dofs", "run_length",
                     "run_dofs", "run_code", "run_point", "run_entity", "kinds",
                     "dof_starts", "dof_shared"):
            delattr(self, name)

        def narrowed(p):
            return (p[0].astype(PETSc.IntType, copy=False), p[1],
                    p[2].astype(np.int16, copy=False), p[6])

        groups = []
        while pending:
            groups.append(narrowed(pending.pop(0)))
        self._layout(groups, store)

    def _extract(self, cells, dofs, offsets, code, nsigma, which, store):
        """New classes for the blocks of the patches `which` of a group, assembled on the
        group's marked owned `cells` with rows at the patches' kept dofs (collective), their rows
        and columns multiplied by the ±1 of G and made canonical a chunk at a time."""
        which = np.asarray(which, dtype=np.int64)
        n = offsets[which + 1] - offsets[which]
        sub = np.concatenate([[0], np.cumsum(n)]).astype(np.int64)
        rows = np.repeat(offsets[which] - sub[:-1], n) + np.arange(sub[-1])
        code = code[rows]
        # room per row: the dofs of the cells holding its dof (two cells for a facet's), at most
        # its patch's
        width = self.W.dofmap.dof_layout.num_dofs
        room = np.where(_kind(code) == FACET, 2 * width, width)
        first, lg = self._block_rows(dofs[rows])
        A = assemble_rows(self.W, cells, lg, np.minimum(room, np.repeat(n, n)))
        del lg, room
        ia, ja, a = A.getValuesCSR()
        A.destroy()
        ia, ja = ia.astype(np.int64), ja.astype(np.int64) - first
        sign = np.where(code & NEGATIVE, -1.0, 1.0)
        a *= np.repeat(sign, np.diff(ia))
        a *= sign[ja]
        out = np.zeros(which.size, dtype=np.int64)
        for lo, hi in self._chunks(sub):
            r0, r1 = sub[lo], sub[hi]
            e0, e1 = ia[r0], ia[r1]
            block = (ia[r0:r1 + 1] - e0, ja[e0:e1] - r0)
            values = canonical_block(*block, a[e0:e1], code[r0:r1], self.blocks)
            out[lo:hi] = store.add(*block, values, sub[lo:hi + 1] - r0, nsigma[which[lo:hi]])
        return out

    def _layout(self, groups, store):
        """Home order (group, size, class multiplicity in the group, class, patch), the routes
        to it, the canonical change of basis in home order, and the inverses of the classes.
        Each group's patches are one slice of the home order, so that a group is gathered,
        solved and scattered in a buffer of its own size (`home_vector`)."""
        comm = self.comm
        ngroups = len(groups)
        n = np.concatenate([np.diff(g[1]) for g in groups])
        cls = np.concatenate([g[3] for g in groups])
        group = np.concatenate([np.full(len(g[1]) - 1, c) for c, g in enumerate(groups)])
        nclasses = store.count()
        shape = np.array([store.shape(k) for k in range(nclasses)], dtype=np.int64)
        shape = shape.reshape(-1, 3)                      # per class (n, L, n_σ)
        # the (group, class) pairs here, each with its patches' count and each patch's pair
        # (no table over all groups and classes: without sharing a class is a patch)
        pairs, pair, count = np.unique(group * nclasses + cls, return_inverse=True,
                                       return_counts=True)
        pair_group, pair_class = pairs // max(nclasses, 1), pairs % max(nclasses, 1)
        # (per group the classes ranked by (n, n_σ, count in the group, class), then the
        # patches by group and rank: a patch's n is its class's)
        rank = np.empty(pairs.size, dtype=np.int64)
        rank[np.lexsort((pair_class, count, shape[pair_class, 2], shape[pair_class, 0],
                         pair_group))] = np.arange(pairs.size)
        order = stable_order(rank[pair])
        del rank
        start = np.zeros(cls.size, dtype=np.int64)
        start[order] = np.cumsum(n[order]) - n[order]
        self.home_size = int(n.sum())
        # each group's slice of the home order [first, last), and its patches' places there
        sizes = np.bincount(group, weights=n, minlength=ngroups).astype(np.int64)
        self.group_starts = np.concatenate([[0], np.cumsum(sizes)])
        self.buffer_size = int(sizes.max(initial=0))
        code = np.zeros(self.home_size, dtype=np.int16)
        # per group the routes from the owners to the home positions: the entries owned here
        # by index lists (`gather`, `scatter`; PETSc 3.18's VecScatter keeps two buffers of
        # their size after its first use), the others by a VecScatter (empty on one process)
        template = PETSc.Vec().createMPI((self.nowned, PETSc.DECIDE), comm=comm)
        hv = local_vec(self.home_vector())
        self.local, self.scatters, self.group_sizes = [], [], []
        index = np.int32 if self.buffer_size < np.iinfo(np.int32).max else np.int64
        lo, hi = self.rstart, self.rstart + self.nowned
        first = 0
        for c, (dofs, offsets, gcode, _) in enumerate(groups):
            k = np.diff(offsets)
            # the group's patches by home position: their entries in home order (a cheaper
            # scatter set-up), those entries' places at home (increasing; the routes count
            # from the group's first) and the entries where these stop counting up by one:
            # the first of a patch that does not follow the one before at home, and among the
            # owned ones the first after another process's
            at = start[first:first + k.size]
            first += k.size
            by_start = np.argsort(at)
            at, k = at[by_start], k[by_start]
            by_home = ranges(offsets[:-1][by_start], k)
            new = np.zeros(by_home.size, dtype=bool)
            jump = np.concatenate([[True], at[1:] != at[:-1] + k[:-1]]) if k.size else k > 0
            new[(np.cumsum(k) - k)[jump]] = True
            at = ranges(at, k)
            code[at] = gcode[by_home]
            at -= self.group_starts[c]
            src = dofs[by_home]
            mine = (src >= lo) & (src < hi)
            new[1:] |= mine[1:] > mine[:-1]
            self.local.append(self._own_route((src[mine] - lo).astype(np.int32, copy=False),
                                              at[mine], np.flatnonzero(new[mine]), index))
            del new
            src = PETSc.IS().createGeneral(src[~mine], comm=PETSc.COMM_SELF)
            dst = PETSc.IS().createGeneral(at[~mine].astype(PETSc.IntType),
                                           comm=PETSc.COMM_SELF)
            self.scatters.append(PETSc.Scatter().create(template, src, hv, dst))
            src.destroy()
            dst.destroy()
            self.group_sizes.append(comm.allreduce(int(offsets[-1]), op=MPI.SUM))
        template.destroy()
        hv.destroy()
        # the patches of group c are order[bounds[c]:bounds[c + 1]]
        bounds = np.concatenate([[0], np.cumsum(np.bincount(group, minlength=ngroups))])
        self.changes = []
        for c in range(ngroups):
            g0, g1 = self.group_starts[c], self.group_starts[c + 1]
            at = start[order[bounds[c]:bounds[c + 1]]] - g0
            self.changes.append(BasisChange(code[g0:g1], np.append(at, g1 - g0), self.blocks))
        del code

        # per class the block of its inverse from the right-hand side entries used to the
        # solution entries wanted (RT dofs first, DG dofs last in a patch), made once per
        # shape (n, n_σ) for all its classes that have none yet (`ClassStore.invert`); per
        # group one product per (shape, count in the group) for all the group's patches of
        # those classes, which take their classes' blocks by index (`solve_home`)
        self.operators, self.solves = store.operators, [[] for _ in range(ngroups)]
        used = np.unique(pair_class)
        ok = True
        try:
            row = store.invert(used)              # a class's block in its shape's
            # the group's classes in home order (each class's first patch: its patches in the
            # group are consecutive there), cut where the shape or the count changes
            new = run_starts(pair[order])
            first, gk, gg = start[order[new]], cls[order[new]], group[order[new]]
            m = count[pair[order[new]]]
            cut = np.flatnonzero(np.diff(np.stack([gg, shape[gk, 0], shape[gk, 2], m]),
                                         axis=1).any(axis=0)) + 1
            for a, b in zip(np.concatenate([[0], cut]).tolist() if gk.size else [],
                            np.concatenate([cut, [gk.size]]).tolist()):
                c, size, rt = int(gg[a]), int(shape[gk[a], 0]), int(shape[gk[a], 2])
                self.solves[c].append((int(first[a] - self.group_starts[c]), b - a, int(m[a]),
                                       size, (size, rt), row[gk[a:b]]))
        except np.linalg.LinAlgError:
            ok = False
        if not comm.allreduce(ok, op=MPI.LAND):
            raise RuntimeError("a patch problem is singular")
        if ok and any(sum(s[1] * s[2] * s[3] for s in self.solves[c])
                      != self.group_starts[c + 1] - self.group_starts[c]
                      for c in range(ngroups)):
            raise RuntimeError("the products do not cover the home vector")
        self.nclasses, self.npatches = used.size, cls.size

    @staticmethod
    def _own_route(rows, at, new, index):
        """The route of a group's entries owned by the home's process: owned W rows `rows`
        to home positions `at` (increasing), which count up by one from each entry `new` on
        to the next. The positions come in runs (a class's patches of one group are
        consecutive at home): runs of at least RUN entries are kept as (home start, entry
        offset, length) and copied as slices, the other entries by their positions."""
        length = np.diff(np.append(new, at.size))
        long = length >= RUN
        runs = list(zip(at[new[long]].tolist(), new[long].tolist(), length[long].tolist()))
        single = ranges(new[~long], length[~long])
        return rows, runs, single.astype(index), at[single].astype(index)

    def home_vector(self):
        """A zero home vector (numpy) for one group at a time: room for the kept dofs of the
        patches at home of the largest group."""
        return np.zeros(self.buffer_size)

    def gather(self, c, b, home):
        """home ← the entries of the W vector b at group c's kept dofs (dolfinx's basis): the
        runs straight into their home slices, the other entries by their positions (PETSc's
        VecGetValues on a sequential Vec over b's owned entries). The group's patches make up
        the first `group_starts[c + 1] - group_starts[c]` entries of the home vector, which
        the gather writes whole: a home vector used before needs no zeroing first."""
        rows, runs, k, at = self.local[c]
        owned = local_vec(b.array_r)
        for h0, k0, n in runs:
            owned.getValues(rows[k0:k0 + n], home[h0:h0 + n])
        home[at] = owned.getValues(rows[k])
        owned.destroy()
        hv = local_vec(home)
        self.scatters[c].scatter(b, hv, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        hv.destroy()
        return home

    def canonical(self, c, home):
        """Gᵀ home in place: group c's gathered right-hand sides in the canonical basis. With
        rhs="divergence" the right-hand sides vanish on the RT dofs, where alone G differs from
        the identity: nothing to do."""
        if self.rhs == "divergence":
            return home
        return self.changes[c].apply(home, transpose=True)

    def solve_home(self, c, home):
        """The solutions of group c's patches for its gathered right-hand sides `home`, as a
        home vector in dolfinx's basis: `home` itself, overwritten."""
        rhs = self.canonical(c, home)
        # K classes of m patches of n dofs each, one inverse per class (its shape's `row`);
        # in place, about SOLVE_CHUNK entries and OPERATOR_CHUNK inverse entries at a time:
        # the inputs are copied out before their slice is overwritten
        for h0, K, m, n, kind, row in self.solves[c]:
            inputs, outputs, operator = self.operators[kind]      # (classes, out, in)
            step = max(1, min(SOLVE_CHUNK // (m * n), OPERATOR_CHUNK // operator[0].size))
            for k0 in range(0, K, step):
                k1 = min(K, k0 + step)
                rows = rhs[h0 + k0 * m * n:h0 + k1 * m * n].reshape(k1 - k0, m, n)
                x = np.matmul(rows[:, :, inputs], operator[row[k0:k1]].transpose(0, 2, 1))
                rows[:, :, outputs] = x
                rows[:, :, outputs.stop:] = 0.0          # (outputs: the first dofs)
        return self.changes[c].apply(rhs, transpose=False)

    def scatter(self, c, x, out, add=False):
        """The solutions of group c (home vector x) into the W vector `out` (owned entries):
        added, or written with zeros at the dofs the group does not keep. The entries owned
        here are added by PETSc's VecSetValues on a sequential Vec over `out`'s owned entries
        (one pass; numpy's owned[rows] += … gathers, adds and scatters), the runs straight
        from their home slices."""
        if not add:
            out.set(0.0)
        rows, runs, k, at = self.local[c]
        owned = local_vec(out.array)
        for h0, k0, n in runs:
            owned.setValues(rows[k0:k0 + n], x[h0:h0 + n], addv=PETSc.InsertMode.ADD_VALUES)
        owned.setValues(rows[k], x[at], addv=PETSc.InsertMode.ADD_VALUES)
        owned.destroy()
        xv = local_vec(x)
        self.scatters[c].scatter(xv, out, PETSc.InsertMode.ADD if add else
                                 PETSc.InsertMode.INSERT, PETSc.ScatterMode.REVERSE)
        xv.destroy()
        return out

    def solve(self, c, b, out=None):
        """Solve group c for the W vector `b`; the W vector `out` holds the solution at the
        kept dofs and zero elsewhere (owned entries)."""
        if out is None:
            out = b.duplicate()
        home = self.gather(c, b, self.home_vector())
        return self.scatter(c, self.solve_home(c, home), out)

    def add_flux(self, x, sigma):
        """sigma.x (owned part) += the RT part of the W vector x (owned part)."""
        n = self.rt_space.dofmap.index_map.size_local
        sigma.x.array[:n] += x.array_r[self.rt_map[:n]]

    def sizes(self):
        """Global number of unknowns of each group's patches."""
        return list(self.group_sizes)

    def stats(self):
        """Global facts of the sharing: patches, classes (distinct inverses, summed over the
        processes), patches whose key's class had another size (a key collision: they have
        their own block), inverse memory in bytes, and facet dofs whose two cells disagree on
        the canonical basis (0)."""
        memory = sum(ops[2].nbytes for ops in self.operators.values())
        local = np.array([self.npatches, self.nclasses, self.collisions, memory, self.disagree])
        total = self.comm.allreduce(local, op=MPI.SUM)
        return dict(zip(("patches", "classes", "collisions", "inverse_bytes", "disagree"),
                        total.tolist()))

    def destroy(self):
        for s in self.scatters:
            s.destroy()
        self.local, self.scatters, self.solves, self.operators = [], [], [], {}
        self.store = None
