"""The set-up side of the patch engine (`patches.PatchSystems`, §5, §12): the local topology,
the owned entities in canonical order (`_canonical_order`), each group's kept dofs at their
patches' homes (`_home_dofs`), the cells whose patch blocks are needed, and the patch blocks
assembled on those cells only.

The dofs of one entity (a facet's RT dofs, a cell's interior RT dofs, a cell's DG dofs) are kept
or not together and are consecutive in the canonical order, so the set-up selects, sorts and
moves *runs* (one per entity, about 2.3 times fewer than the dofs) and expands them to dofs once,
at the homes.

A kept dof of a patch is supported on that patch's cells only, so the principal submatrix of A
(forms.equilibration.patch_system) on a patch's kept dofs is the same whether A is assembled
over the whole mesh or over any set of cells containing the patch's cells, and whatever is done
with the other dofs: `assemble_rows` assembles A on the cells of one group's patches whose blocks
are taken, into a matrix that has rows and columns for those patches' kept dofs only, numbered
at their homes patch after patch (`_block_rows`): its local rows are the blocks themselves.
"""

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

from ..forms import equilibration as equilibration_forms
from .congruence import DG, INTERIOR, _kind, patch_keys
from .exchange import (
    Shared,
    alltoallv,
    reduce_by_key,
    run_starts,
    stable_order,
)

CHUNK = 1 << 18          # rows of patch blocks made canonical at a time (bounds the set-up memory)


class HomeSetup:
    """The set-up methods of `patches.PatchSystems` (a mixin)."""

    @staticmethod
    def _chunks(offsets):
        """Ranges of patches (first, last) of about CHUNK rows each."""
        npatch = len(offsets) - 1
        count = max(1, -(-int(offsets[-1]) // CHUNK))
        bounds = np.searchsorted(offsets, np.linspace(0, offsets[-1], count + 1)[1:-1])
        bounds = np.concatenate([[0], np.minimum(bounds, npatch), [npatch]])
        return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))

    def _topology(self, mesh, W, rt, dg):
        """Cell → facet and cell → dof tables (all local cells), facets with one or two cells
        (global); `rt`, `dg`: W.sub(0), W.sub(1)."""
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
        # the (at most two) owned cells of each local facet (two arrays, -1: none), from the
        # facet → cell table (its cells, owned or ghost); and whether a facet has two cells or
        # one over the whole mesh (owned cells only, each counted by its owner)
        f2c = mesh.topology.connectivity(tdim - 1, tdim)
        first, ncell = f2c.offsets[:-1], np.diff(f2c.offsets)
        if np.any((ncell < 1) | (ncell > 2)):
            raise RuntimeError("a facet without cells or with more than two")
        a = f2c.array[first].astype(np.int64)
        b = np.where(ncell == 2, f2c.array[np.minimum(first + 1, f2c.array.size - 1)], -1)
        self.facet_owned_cells = [np.where(c < self.ncells, c, -1).astype(np.int64) for c in (a, b)]
        count = np.bincount(self.c2f[:self.ncells].ravel(), minlength=self.nfacets)
        count = self.facet_shared.forward(self.facet_shared.reverse(count, np.add))
        self.facet_two, self.facet_one = count == 2, count == 1

        # (by the dofs per cell: a process may hold no cell at all)
        rt_map, dg_map = rt.dofmap, dg.dofmap
        rt = rt.element.basix_element.entity_dofs
        self.rt_dofs = rt_map.list.array.reshape(nall, rt_map.dof_layout.num_dofs)
        self.dg_dofs = dg_map.list.array.reshape(nall, dg_map.dof_layout.num_dofs)
        # the RT dofs of each local facet, and the interior RT and DG dofs of each local cell
        self.facet_dofs = np.zeros((self.nfacets, len(rt[tdim - 1][0])), dtype=np.int32)
        for i, cols in enumerate(rt[tdim - 1]):
            self.facet_dofs[self.c2f[:, i]] = self.rt_dofs[:, cols]
        self.cell_dofs = np.hstack([self.rt_dofs[:, rt[tdim][0]], self.dg_dofs])
        # the coordinates of the local cells' nodes (cells, 3, 2), for `canonical_dofs` too,
        # and the shortest edge of each owned cell (the unit of the patch keys' positions)
        self.cell_xy = mesh.geometry.x[:, :2][mesh.geometry.dofmap.array.reshape(-1, 3)[:nall]]
        x, y = self.cell_xy[:self.ncells, :, 0], self.cell_xy[:self.ncells, :, 1]
        for i, j in ((0, 2), (1, 0), (2, 1)):                 # the edges x_i - x_j
            dx, dy = x[:, i] - x[:, j], y[:, i] - y[:, j]
            dx *= dx
            dy *= dy
            dx += dy
            self.cell_h = dx if i == 0 else np.minimum(self.cell_h, dx, out=self.cell_h)
        np.sqrt(self.cell_h, out=self.cell_h)
        imap = W.dofmap.index_map
        self.nowned = imap.size_local
        self.nlocal = imap.size_local + imap.num_ghosts
        self.rstart = imap.local_range[0]
        self.dof_starts = np.array(self.comm.allgather(int(self.rstart)), dtype=np.int64)
        self.dof_shared = Shared(imap, self.comm)

    def _canonical_order(self, facet_point, cell_point):
        """The entities as *runs* of dofs: a facet's RT dofs, a cell's interior RT dofs, a
        cell's DG dofs, each by index; and the owned entities in canonical order. The canonical
        order of the dofs in a patch is by kind, position along the direction, entity and index
        (`congruence`), and an entity's dofs share kind and position (`facet_point`,
        `cell_point`: of the local facets and cells), so the owned entities of each kind are
        sorted (by position and global index) and their dofs follow them. Kept: per run its
        dofs (local indices, padded with -1) and codes, length, position and entity (global
        index and kind), the runs of a kind from its first on in the entities' local order
        (local facets, owned cells: the mesh's order, in which a patch's entities lie close);
        per kind its owned entities in canonical order and its first run. A patch keeps whole
        entities, so `_home_dofs` selects and sorts runs, not dofs.

        The rows of dofs and codes are padded (dofs -1, codes -1: real codes are ≥ 0) to a
        power of two entries, 16 or 8 bytes for 3 dofs, which numpy's np.take gathers as
        single words and elementwise operations see as contiguous rows."""
        n = self.nowned
        inner = self.cell_dofs.shape[1] - 3                  # interior RT dofs, then DG1's 3
        tables = [self.facet_dofs, self.cell_dofs[:, :inner], self.cell_dofs[:, inner:]]
        fmap, cmap = (self.mesh.topology.index_map(d) for d in (1, 2))
        fglobal, cglobal = (np.asarray(m.local_to_global(np.arange(k, dtype=np.int32)),
                                       dtype=np.int64)
                            for m, k in ((fmap, self.nfacets), (cmap, len(self.cell_dofs))))
        entities = [(fglobal, facet_point), (cglobal, cell_point), (cglobal, cell_point)]
        sorted_rows, done = [], {}                 # done: the cells' order, for both tables
        for table, (glob, point) in zip(tables, entities):
            # the columns (dofs and their codes) by index in the entity (often already so: then
            # the table itself); the owned rows by position and global index
            codes = self.code[table]
            index = codes & 3
            if not np.array_equal(index, np.broadcast_to(np.arange(table.shape[1]), index.shape)):
                index = index.astype(np.int64)
                by_index, ordered = np.full_like(table, -1), np.full_like(codes, -1)
                np.put_along_axis(by_index, index, table, axis=1)
                np.put_along_axis(ordered, index, codes, axis=1)
                table, codes = by_index, ordered
            del index
            by_index = table
            if np.any(by_index < 0):
                raise RuntimeError("an entity's dofs are not indexed 0, 1, ...")
            owned = by_index < n                      # all and any by columns (a few)
            mine, some = owned[:, 0].copy(), owned[:, 0].copy()
            for column in owned.T[1:]:
                mine &= column
                some |= column
            if np.any(some != mine):
                raise RuntimeError("an entity's dofs have several owners")
            rows = np.flatnonzero(mine)
            seen = done.get(id(glob))
            if seen is None or not np.array_equal(seen[0], rows):
                seen = done[id(glob)] = (rows, rows[np.lexsort((glob[rows], point[rows, 0]))])
            sorted_rows.append((by_index, codes, seen[1]))
        # the runs of the kinds FACET, INNER, DG one after the other
        size = [self.nfacets, self.ncells, self.ncells]          # runs of each kind
        total = sum(size)
        width = max(table.shape[1] for table in tables)
        padded = 1 << (width - 1).bit_length()
        self.run_dofs = np.full((total, padded), -1, dtype=np.int32)
        self.run_code = np.full((total, padded), -1, dtype=np.int16)
        self.run_length = np.zeros(total, dtype=np.int64)
        self.run_point = np.zeros((total, 2))
        self.run_entity = np.zeros(total, dtype=np.int64)
        self.kinds, first = [], 0
        for kind, ((by_index, codes, rows), (glob, point), m) in enumerate(
                zip(sorted_rows, entities, size)):
            last, k = first + m, by_index.shape[1]
            if kind and (rows.size != self.ncells or rows.max(initial=-1) >= self.ncells):
                raise RuntimeError("a cell's own dofs are not owned by the cell's owner")
            self.kinds.append((rows, first))
            self.run_dofs[first:last, :k] = by_index[:m]
            self.run_code[first:last, :k] = codes[:m]
            self.run_length[first:last] = k
            self.run_point[first:last] = point[:m]
            self.run_entity[first:last] = 4 * glob[:m] + kind
            first = last
        del self.facet_dofs, self.cell_dofs

    def _home_dofs(self, pid, inner):
        """The kept W dofs of the group's patches at home on this process (global indices, as
        PETSc's integers), in canonical order patch by patch (RT facet dofs, interior RT dofs,
        DG dofs), the patches' offsets, the dofs' codes, the patches' numbers of RT dofs, their
        keys and their ids; and the group's owned cells patch by patch, their number per patch
        and the patches' ids (for `_marked_cells`). A collective call: every process hands over
        its owned kept dofs."""
        comm = self.comm
        # per facet, over its (at most two) cells: the largest and smallest of 2 (patch id + 1)
        # + (the patch is not interior) (0 = no patch; the flag is the patch's, so the two
        # agree when the patch ids do); reduced across processes. A missing cell (-1) gives
        # the least int64 in both columns (the least int64 is its own negative).
        tag = np.empty(pid.size + 1, dtype=np.int64)
        np.add(pid, 1, out=tag[:-1])
        tag[:-1] <<= 1
        tag[:-1] |= ~inner & (pid >= 0)
        tag[-1] = np.iinfo(np.int64).min
        first, second = (tag.take(cells) for cells in self.facet_owned_cells)
        info = np.empty((first.size, 2), dtype=np.int64)
        np.maximum(first, second, out=info[:, 0])
        np.maximum(np.negative(first, out=first), np.negative(second, out=second),
                   out=info[:, 1])
        del tag, first, second
        self.facet_shared.forward(self.facet_shared.reverse(info, np.maximum))
        # kept: both cells in one patch, or the one cell of a facet on ∂Ω in a patch that is
        # not interior
        hi = info[:, 0]
        keep = hi == np.negative(info[:, 1], out=info[:, 1])
        keep &= hi > 0
        keep &= self.facet_two | (self.facet_one & (hi & 1).astype(bool))
        hi >>= 1
        facet_patch = np.where(keep, hi, 0) - 1
        del info, hi, keep

        # the runs the group keeps, patch by patch: per kind its owned entities in canonical
        # order whose patch keeps them, stably by patch (as int32 when the patch ids fit: half
        # the memory traffic of the sort), then per patch its kinds one after the other (FACET,
        # INNER, DG: the canonical order); the two kinds of the cells share one sort
        top = max(int(pid.max(initial=-1)), int(facet_patch.max(initial=-1)))
        small = top < np.iinfo(np.int32).max
        picked, done = [], {}
        for (rows, base), patch_of in zip(self.kinds, (facet_patch, pid, pid)):
            key = (id(rows), id(patch_of))
            if key not in done:
                p = patch_of[rows]
                at = np.flatnonzero(p >= 0)
                entity, p = rows[at], (p[at].astype(np.int32) if small else p[at])
                order = stable_order(p)
                entity, p = entity[order], p[order]
                new = run_starts(p)
                done[key] = (entity, p, new, np.diff(np.append(new, p.size)))
            picked.append((base,) + done[key])
        seen = np.unique(np.concatenate([p[new] for _, _, p, new, _ in picked])).astype(np.int64)
        where = [np.searchsorted(seen, p[new]) for _, _, p, new, _ in picked]
        count = np.zeros(seen.size, dtype=np.int64)                 # runs per patch
        for at, (_, _, _, _, n) in zip(where, picked):
            count[at] += n
        before = np.cumsum(count) - count                      # runs before each kind's
        runs = np.empty(int(count.sum()), dtype=np.int64)
        for at, (base, entity, p, new, n) in zip(where, picked):
            runs[np.repeat(before[at] - new, n) + np.arange(p.size)] = entity + base
            before[at] += n
        del before, where

        # home of each patch: the owner of its cell of least global index, found with the
        # patch's interior flag in one distributed reduction over the patches seen here
        # (and its shortest edge); its owned cells, patch by patch, are kept for
        # `_marked_cells`
        by_cell, p, new, n = done[(id(self.kinds[1][0]), id(pid))]
        keys = p[new].astype(np.int64)
        owned = (by_cell.astype(np.int32), n, keys)
        values = ((self.cell_global[by_cell] * comm.size + comm.rank) << 1) | ~inner[by_cell]
        values = np.minimum.reduceat(values, new) if new.size else values[:0]
        h = np.minimum.reduceat(self.cell_h[by_cell], new) if new.size else np.zeros(0)
        del done, picked, by_cell, p, new, n
        extra = seen[keys[np.minimum(np.searchsorted(keys, seen), keys.size - 1)] != seen] \
            if keys.size else seen                      # patches with no owned cell here
        if extra.size:
            keys = np.concatenate([keys, extra])
            values = np.concatenate([values, np.full(extra.size, np.iinfo(np.int64).max)])
            h = np.concatenate([h, np.full(extra.size, np.inf)])
            order = np.argsort(keys)
            keys, values, h = keys[order], values[order], h[order]
        at = np.searchsorted(keys, seen)
        first = reduce_by_key(comm, keys, values, np.minimum)[at]
        h = reduce_by_key(comm, keys, h, np.minimum)[at]
        home = (first >> 1) % comm.size
        interior = np.where(first & 1, np.int16(0), np.int16(INTERIOR))

        # every kept run goes to its patch's home, which keeps the patches whole. A patch at
        # home here with all its runs here keeps them where they are, in `runs`' order (by
        # patch, canonical within each); only the other runs travel, column by column. Those
        # of a *mixed* patch (runs on several processes: the others tell its home first) are
        # merged at its home in canonical order, after the patches that stay.
        away = home != comm.rank
        mixed = np.zeros(seen.size, dtype=bool)
        if comm.size > 1:
            to = home[away]
            by_home = stable_order(to)
            told_counts = np.bincount(to, minlength=comm.size).astype(np.int64)
            told = alltoallv(comm, seen[away][by_home], told_counts,
                             np.asarray(comm.alltoall(told_counts.tolist()), dtype=np.int64))
            place = np.minimum(np.searchsorted(seen, told), max(seen.size - 1, 0))
            if told.size and not np.array_equal(seen[place], told):
                raise RuntimeError("a patch's home holds none of its runs")
            mixed[place] = True
            del to, by_home, told, place
        run_patch, run_interior = np.repeat(seen, count), np.repeat(interior, count)
        run_h = np.repeat(h, count)
        del h, first, at, interior
        if comm.size == 1:
            keep, tail = slice(None), None
        else:
            where = np.repeat(np.where(away, 2, mixed).astype(np.int8), count)
            keep = np.flatnonzero(where == 0)
            sent = np.flatnonzero(where == 2)
            sent = sent[stable_order(np.repeat(home, count)[sent])]       # by home
            tail = (np.flatnonzero(where == 1), sent)
            del where
            send = np.bincount(home[away], weights=count[away],
                               minlength=comm.size).astype(np.int64)
            recv = np.asarray(comm.alltoall(send.tolist()), dtype=np.int64)

        # the columns: per run its patch, length, dofs (global), codes (with the patch's
        # interior flag), position and the patch's shortest edge; (table, indexed by the runs'
        # entities or by their positions in `runs`, what is added or or-ed in)
        columns = [(run_patch, False, None), (self.run_length, True, None),
                   (self.run_dofs, True, "dofs"), (self.run_code, True, "code"),
                   (self.run_point, True, None), (run_h, False, None)]

        def take(table, positions, by_run, finish):
            # (np.take of padded rows: numpy's fast gather of small rows; -1 past a run's dofs)
            values = table.take(runs[positions] if by_run else positions, axis=0)
            return finished(values, positions, finish)

        def finished(values, positions, finish):
            if finish == "dofs":
                values += PETSc.IntType(self.rstart)
            elif finish == "code":
                values |= run_interior[positions][:, None]
            return values

        if tail is None:                  # one process: every run stays, in `runs`' order
            columns = [take(table, slice(None), True, finish) if by_run else table
                       for table, by_run, finish in columns]
        else:
            # the mixed patches' runs (own, then received) by patch, then in canonical order
            # (kind, position, entity), as `runs` orders a patch's runs; after those that stay
            own, sent = tail

            def mixed_part(table, by_run, finish=None):
                return np.concatenate([take(table, own, by_run, finish),
                                       alltoallv(comm, take(table, sent, by_run, finish),
                                                 send, recv)])

            parts = [mixed_part(*c) for c in columns]
            entity = mixed_part(self.run_entity, True)
            merge = np.lexsort((entity, parts[4][:, 0], _kind(parts[3][:, 0]), parts[0]))
            del entity
            stay = runs[keep]
            for k, ((table, by_run, finish), part) in enumerate(zip(columns, parts)):
                out = np.empty((keep.size + part.shape[0],) + table.shape[1:], table.dtype)
                np.take(table, stay if by_run else keep, axis=0, out=out[:keep.size])
                finished(out[:keep.size], keep, finish)
                out[keep.size:] = part[merge]
                columns[k] = out
            del parts, stay
        gpatch, glength, gdofs, gcode, gpoint, gh = columns
        columns = run_patch = run_interior = run_h = None      # (freed)
        received = gpatch.size
        # patch offsets; interior patches lose their first DG dof, the first of their first
        # DG run (the DG runs come last in a patch, so the runs before are its RT dofs)
        new = run_starts(gpatch)
        dg = np.flatnonzero(_kind(gcode[:, 0]) == DG)
        first_dg = dg[run_starts(gpatch[dg])]
        if first_dg.size != new.size:
            raise RuntimeError("a patch without DG dofs")
        before = np.zeros(received + 1, dtype=np.int64)               # dofs before each run
        np.cumsum(glength, out=before[1:])
        nsigma = before[first_dg] - before[new]
        pinned = first_dg[(gcode[first_dg, 0] & INTERIOR) != 0]         # runs
        kept = gcode >= 0                                                # (runs, index)
        kept[pinned, 0] = False
        size = glength.copy()
        size[pinned] -= 1
        np.cumsum(size, out=before[1:])
        start = before[np.append(new, received)]
        kept = np.flatnonzero(kept)                          # (np.take: faster than a mask)
        dofs, code = gdofs.take(kept), gcode.take(kept)
        del kept
        h = gh[new]
        # the keys hash the first dof of each run, one per entity of the patch (a pinned
        # run's too: translated patches pin the same run), and the patch's kept dofs
        key = patch_keys(np.append(new, received), gcode[:, 0], gpoint, h, np.diff(start))

        return dofs, start, code, nsigma, key, gpatch[new], owned

    def _marked_cells(self, owned, chosen):
        """Per group c, the owned cells (local indices, increasing) of its patches `chosen[c]`
        (global patch ids, each listed by its home only; the patches' cells may live on other
        processes), from `owned[c]`: the group's owned cells patch by patch, their number per
        patch and the patches' ids (`_home_dofs`). Collective: one reduction over (patch,
        group) keys."""
        ngroups = len(owned)
        keys, values = [], []
        for c, (_, _, ids) in enumerate(owned):
            keys += [ids * ngroups + c, np.asarray(chosen[c], dtype=np.int64) * ngroups + c]
            values += [np.zeros(ids.size, dtype=np.int8), np.ones(len(chosen[c]), np.int8)]
        flag = reduce_by_key(self.comm, np.concatenate(keys), np.concatenate(values),
                             np.maximum)
        marked, at = [], 0
        for c, (by_patch, count, ids) in enumerate(owned):
            mark = np.zeros(self.ncells, dtype=bool)
            mark[by_patch] = np.repeat(flag[at:at + ids.size] > 0, count)
            marked.append(np.flatnonzero(mark).astype(np.int32))
            at += ids.size + len(chosen[c])
        return marked

    def _block_rows(self, dofs):
        """The rows of `assemble_rows` for the kept dofs `dofs` (global W indices) of the
        patches of one group whose blocks are taken at home here, patch after patch: numbered
        in that order, after those of the lower ranks. Returns the first row here and the row of
        every local W dof (owned and ghost; -1: none), which the homes send to the dofs'
        owners and these to their ghosts. Collective."""
        comm = self.comm
        first = comm.exscan(dofs.size, op=MPI.SUM) or 0                # (None on rank 0)
        owner = np.searchsorted(self.dof_starts, dofs, side="right") - 1
        order = stable_order(owner) if comm.size > 1 else slice(None)
        send = np.bincount(owner, minlength=comm.size).astype(np.int64)
        recv = np.asarray(comm.alltoall(send.tolist()), dtype=np.int64)
        at = alltoallv(comm, dofs[order], send, recv) - self.rstart
        rows = np.full(self.nlocal, -1, dtype=PETSc.IntType)
        rows[at] = alltoallv(comm, np.arange(first, first + dofs.size)[order], send, recv)
        return first, self.dof_shared.forward(rows)


def assemble_rows(W, cells, rows, room):
    """A = forms.equilibration.patch_system assembled by dolfinx on the owned `cells` (local
    indices) only, into a PETSc matrix whose row and column of local W dof i is rows[i] (-1:
    the dof is left out), with len(room) local rows, local row k with room for room[k] entries,
    all in the diagonal block (a patch's rows are at its home). No matrix over the whole of W
    is made (dolfinx's sparsity pattern keeps a list per row of W). Collective."""
    from dolfinx import fem
    from dolfinx.fem.petsc import assemble_matrix
    from dolfinx.mesh import meshtags
    mesh, comm = W.mesh, W.mesh.comm
    size = len(room)
    total = comm.allreduce(size, op=MPI.SUM)
    # (petsc4py mishandles empty arrays of row lengths: no rows here, no lengths)
    nnz = (np.asarray(room, dtype=PETSc.IntType), np.zeros(size, dtype=PETSc.IntType)) \
        if size else (0, 0)
    A = PETSc.Mat().createAIJ(((size, total), (size, total)), nnz=nnz, comm=comm)
    lgmap = PETSc.LGMap().create(rows, comm=comm)
    A.setLGMap(lgmap, lgmap)
    lgmap.destroy()
    cells = np.asarray(cells, dtype=np.int32)
    tags = meshtags(mesh, mesh.topology.dim, cells, np.ones(cells.size, dtype=np.int32))
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=tags)(1)
    (sigma, gamma), (tau, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
    assemble_matrix(A, fem.form(equilibration_forms.patch_system(sigma, gamma, tau, q, dx)))
    A.assemble()
    return A
