"""The discretisation flux σ_α,disc by patchwise mixed Raviart–Thomas problems (§5, §12).

For each vertex a and membrane α, on the patch ω_a (cells sharing a), RT_1 × DG1:

    (σ_a, τ) - (γ_a, ∇·τ) = -(ψ_a μ_α ∇u_αh, τ)      ∀ τ ∈ V_h^a
    (∇·σ_a, q)            = (g̃_a, q)                   ∀ q ∈ Q_h^a
    g̃_a = ψ_a (f_α ± λ_a - r_αh) - μ_α ∇u_αh·∇ψ_a       (+ for α = 1, - for α = 2)

V_h^a: zero normal flux on ∂ω_a \\ ∂Ω; Q_h^a: zero mean if a ∉ ∂Ω. σ_α,disc = Σ_a σ_a, so that
∇·σ_α,disc = Π_P1 f_α ± λ_h - r_αh on every cell (Σ_a ψ_a = 1, Σ_a λ_a ψ_a = λ_h,
Σ_a ∇ψ_a = 0).

Distributed set-up (§12): the vertices are coloured so that no two vertices of one colour share
a cell (`patches.colour_vertices`); the patches of the vertices of colour c are then group c of
`patches.PatchSystems`, set up once per mesh (congruent patches share one dense inverse). Per
call and colour the right-hand side is ONE dolfinx assembly of `forms.equilibration.patch_rhs`
(over the cells touching colour c) with the P1 coefficients ψ_c = Σ_{a of colour c} ψ_a and
Λ_c = Σ_{a of colour c} λ_a ψ_a (on a patch of colour c they are ψ_a and λ_a ψ_a), plus the data
part -(ψ_c f, q), which does not change with the iterate: it is assembled once per mesh for
both loads (`assemble_loads`: one assembly for all colours, since it lives on the cell-local DG1
dofs) and added to the colour's assembled vector at its DG1 dofs. All patches are then solved
at once; the RT parts of the colours' solutions add up to σ_α,disc.

Cost (§12). Each cell touches three colours, so the per-call assemblies run the kernel three
times per cell; the kernel and dolfinx's packing of the coefficients (a gather per cell and
coefficient) are most of a call besides the patch solves. ψ_c, Λ_c and u_αh are therefore the
components of one vector-P1 Function (one gather per vertex, not three), and the per-call work
outside dolfinx is kept to writing those components.

Compatibility of the interior patches, (g̃_a, 1) = 0, is the linear row of §4 at a: it holds
to round-off only if (ψ_a f, 1) is integrated here with the same quadrature as the load
F_α = ((f_α, ψ_a))_a of the discretisation, so `Load` uses the data measures (dx_data) that
assembled F_α. With another rule the defect, a quadrature error, lands on one cell per
interior patch (`patches`, the pinned dof).
"""

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

from ..fem.discretisation import boundary_dofs, ghosted_vector
from ..fem.meshes import cell_vertices, triangle_areas
from ..forms import equilibration as equilibration_forms
from .cell_forms import compiled
from .divergence import assemble, check, largest, norm_squared
from .patches import PatchSystems, colour_vertices, local_vec

PSI, LAMC, U = range(3)      # components of FluxEquilibration.nodal


def same_numbering(V, W):
    """Whether the spaces V, W (of one mesh) number their nodes alike: equal cell dofmaps and
    index maps (owned sizes and ghosts), so that node i of V is node i of W (block sizes may
    differ). Local: reduce over the processes before acting on it."""
    a, b = V.dofmap.index_map, W.dofmap.index_map
    return bool(np.array_equal(V.dofmap.list.array, W.dofmap.list.array)
                and a.size_local == b.size_local and np.array_equal(a.ghosts, b.ghosts))


def nodal_function(V, dim):
    """A vector-P1 Function of `dim` components on V's mesh that numbers its vertices as the P1
    space V does (checked on every process; collective): the nodal fields of a form packed as
    one coefficient, one gather per vertex when dolfinx packs a cell."""
    from dolfinx import fem
    f = fem.Function(fem.VectorFunctionSpace(V.mesh, ("Lagrange", 1), dim=dim))
    if not V.mesh.comm.allreduce(same_numbering(f.function_space, V), op=MPI.LAND):
        raise RuntimeError("vector P1 numbers its vertices unlike P1")
    return f


def colour_cells(colour, cells, ncolours):
    """Per colour c: the cells (rows of `cells`, ascending) with a vertex of colour c and, on
    each, the local index of that vertex (one at most, by the colouring); one stable sort
    (of int8 keys when the colours fit: numpy then sorts by radix)."""
    flat = colour[cells].ravel()                                   # cell-major: 3 cell + slot
    if flat.size and -128 <= flat.min() and flat.max() < 128:
        flat = flat.astype(np.int8)
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(ncolours + 1))
    return [((order[a:b] // 3).astype(np.int32), (order[a:b] % 3).astype(np.int8))
            for a, b in zip(bounds[:-1], bounds[1:])]


def vertex_patches(V, colour, ncolours, on_boundary, touching=None):
    """The groups of `PatchSystems` for the vertex patches of §5: per colour c, over the owned
    cells, the global index of the cell's vertex of colour c (-1: none; one at most, by the
    colouring) and whether that vertex is off ∂Ω (an interior patch). `touching`: the
    `colour_cells` of the owned cells, if at hand."""
    nc = V.mesh.topology.index_map(V.mesh.topology.dim).size_local
    cells = V.dofmap.list.array.reshape(-1, 3)[:nc]
    gdofs = np.asarray(V.dofmap.index_map.local_to_global(np.arange(colour.size,
                                                                    dtype=np.int32)),
                       dtype=np.int64)
    if touching is None:
        touching = colour_cells(colour, cells, ncolours)
    patches, interior = [], []
    for hit, slot in touching:
        vertex = cells[hit, slot]
        patch = np.full(nc, -1, dtype=np.int64)
        patch[hit] = gdofs[vertex]
        inner = np.zeros(nc, dtype=bool)
        inner[hit] = ~on_boundary[vertex]
        patches.append(patch)
        interior.append(inner)
    return patches, interior


class Load:
    """The data part -(ψ_c f, q) of the patch right-hand sides of all colours, assembled with
    the data measures once per load f and mesh and added at every call of `sigma` to the
    colour's assembled right-hand side: `values[c]` (cells touching colour c, 3) holds it at
    the DG1 dofs `FluxEquilibration.dg_dofs(c)` of those cells (the only dofs where it is not
    zero). Made by `FluxEquilibration.loads` (several loads in one assembly) or `load`."""

    def __init__(self, f, values):
        self.f, self.values = f, values


def assemble_loads(eq, fs, measures):
    """(loads, moments): the `Load`s of the expressions `fs` on the mesh of `eq` (a
    FluxEquilibration), and (owned cells, 3, len(fs)) (f_i, q_m)_K for the DG1 basis q_m of
    each cell, the loads of the fs' DG1 projections (η_osc, §7): the sum over the slots below,
    since Σ_s φ_s = 1.

    The data part lives on the DG1 dofs, which belong to one cell each: on a cell K touching
    colour c it is -(φ_j f, q_m)_K, φ_j the hat function of K's vertex of colour c. So one
    assembly gives it for every colour and every load: the test function is vector DG1 with
    three components q_{3i+s} per load f_i, and component 3i + s is tested against φ_s, the hat
    of K's local vertex s (DG1 Functions, `FluxEquilibration.slots`): the result holds the
    3 × 3 block -(φ_s f_i, q_m)_K of every cell, and colour c takes column s = (local index of
    its vertex) on each cell touching it. The data are integrated once per cell instead of once
    per colour and load, with the same measures and integrand (the compatibility above holds
    as before)."""
    from dolfinx import fem, la

    from membranes.fem.quadrature import over
    k = len(fs)
    hats = eq.slots()
    Z = fem.VectorFunctionSpace(eq.mesh, ("DG", 1), dim=3 * k)
    q = ufl.TestFunction(Z)
    form = fem.form(over(measures, lambda dx: sum(
        equilibration_forms.patch_load(hats[s], f, q[3 * i + s], dx)
        for i, f in enumerate(fs) for s in range(3))))
    vector = fem.assemble_vector(form)
    # (the form and the hats, 9 doubles a cell, go before the blocks are read: the first full
    # evaluation makes the loads, and what is alive here adds to its peak)
    del form
    hats.clear()
    vector.scatter_reverse(la.ScatterMode.add)
    blocks = vector.array                         # entry 3k z + 3i + s: dof z, load i, slot s
    nc = eq.cells.shape[0]
    zdofs = Z.dofmap.list.array.reshape(-1, 3)[:nc]
    # Σ_s -(φ_s f_i, q_m)_K = -(f_i, q_m)_K: per cell, DG1 dof m and load i (no copy by the
    # cells where Z's dofs follow them); slot by slot (numpy reduces an axis of three slowly),
    # into one array
    slots = blocks.reshape(-1, k, 3)
    moments = np.add(slots[:, :, 0], slots[:, :, 1])
    moments += slots[:, :, 2]
    np.negative(moments, out=moments)
    del slots
    follow = np.array_equal(zdofs, np.arange(3 * nc).reshape(-1, 3))
    moments = moments[:3 * nc].reshape(nc, 3, k) if follow else moments.take(zdofs, axis=0)
    values = [[] for _ in fs]
    for touching, s in eq.touching():
        entry = 3 * k * zdofs[touching].astype(np.int64) + s[:, None]
        for i in range(k):
            values[i].append(blocks[entry + 3 * i])
    return [Load(f, v) for f, v in zip(fs, values)], moments


class FluxEquilibration:
    """σ_α,disc on one mesh (§5): colouring, patch systems and factorisations set up once.

    `FluxEquilibration(V_or_disc, measures=None)`: V the P1 space, or a Discretisation (its V and
    data measures dx_data are used). `sigma(alpha, u, lam, r, f, mu, out=None)` returns σ_α,disc
    as a Function of `rt_space` (RT_1): u the P1 Function u_αh, lam the P1 Function λ_h (nodal
    values λ_a), r the DG1 Function r_αh (`lifting.Lifting`), f a UFL expression of f_α or a
    `Load` from `load(f)` or `loads([f1, f2])` (one assembly for several loads; an expression
    is turned into a Load at its first use and kept), mu the float μ_α.
    """

    def __init__(self, V, measures=None):
        from dolfinx import fem
        if hasattr(V, "V"):                               # a Discretisation
            measures = measures if measures is not None else getattr(V, "dx_data", None)
            V = V.V
        self.V, self.mesh, self.comm = V, V.mesh, V.mesh.comm
        self.measures = measures
        mesh = self.mesh
        nc = mesh.topology.index_map(mesh.topology.dim).size_local
        self.cells = cells = V.dofmap.list.array.reshape(-1, 3)[:nc]
        imap = V.dofmap.index_map
        self.colour, self.ncolours, self.colour_rounds = colour_vertices(cells, imap, self.comm)
        self.on_boundary = boundary_dofs(V)
        self._touching = self._home = self._dg_dofs = None
        patches, interior = vertex_patches(V, self.colour, self.ncolours, self.on_boundary,
                                           self.touching())
        self.systems = PatchSystems(mesh, patches, interior, solution="flux")
        self.rt_space = self.systems.rt_space

        # coefficients of the right-hand side forms, compiled once
        # ψ_c, Λ_c and u_αh are the components PSI, LAMC, U of one vector-P1 Function: dolfinx
        # packs a form's coefficients cell by cell, and a vertex's values then lie side by side
        # (one gather instead of three). It numbers the vertices as V does (checked).
        self.nodal = nodal_function(V, 3)
        self._nodal = self.nodal.x.array.reshape(-1, 3)
        self.lam = fem.Function(V)
        self.r = fem.Function(fem.FunctionSpace(mesh, ("DG", 1)))
        self.mu = fem.Constant(mesh, 1.0)
        self.sign = fem.Constant(mesh, 1.0)
        tau, q = ufl.TestFunctions(self.systems.W)
        # one form per colour, integrated over the cells touching the colour (elsewhere ψ_c
        # and Λ_c vanish); the same compiled kernel, the cell tags are data
        from dolfinx import mesh as dmesh
        owned = np.arange(nc, dtype=np.int32)
        parts = []
        for touching, _ in self.touching():
            marker = np.zeros(nc, dtype=np.int32)
            marker[touching] = 1
            tags = dmesh.meshtags(mesh, mesh.topology.dim, owned, marker)
            dx = ufl.Measure("dx", domain=mesh, subdomain_data=tags)(1)
            parts.append(equilibration_forms.patch_rhs(
                self.nodal[PSI], self.nodal[LAMC], self.sign, self.mu, self.nodal[U], self.r,
                tau, q, dx))
        self.rhs_forms = compiled(parts, mesh)             # (one JIT lookup for the colours)
        self._b = self._x = None
        self._loads = {}
        self.defect = None           # the relative divergence defect of the last σ made
        self.defect_sq = None        # ‖∇·σ_α,disc - (Π f ± λ - r)‖² of the last σ made (global)
        # |K| of the owned cells for the defect's norm: the Estimators hand over their
        # lifting's (the same cells), else made at the first check
        self.area = None

    @property
    def b(self):
        """One W vector for the colours' right-hand sides, one colour at a time: made at the
        first `sigma` (not alive under the Newton steps before the first full estimate)."""
        if self._b is None:
            # (not dolfinx's create_vector: one left unreleased, by an exception between
            # `sigma` and `release`, would never be freed; `ghosted_vector`)
            self._b = ghosted_vector(self.rhs_forms[0].function_spaces[0])
        return self._b

    @property
    def x(self):
        """The W vector (owned entries) where the colours' solutions add up: made at the first
        `sigma`, like b."""
        if self._x is None:
            W = self.systems.W
            self._x = PETSc.Vec().createMPI((W.dofmap.index_map.size_local, PETSc.DECIDE),
                                            comm=self.comm)
        return self._x

    def touching(self):
        """`colour_cells` of the owned cells: per colour c the cells touching c and the local
        index of their vertex of colour c. Built once per mesh."""
        if self._touching is None:
            self._touching = colour_cells(self.colour, self.cells, self.ncolours)
        return self._touching

    def slots(self):
        """The hats for `assemble_loads`: hats[s] the DG1 Function (of the space of r) equal on
        every cell to the hat function of its local vertex s."""
        from dolfinx import fem
        Q = self.r.function_space
        cells = Q.dofmap.list.array.reshape(-1, 3)
        hats = [fem.Function(Q) for _ in range(3)]
        for s, hat in enumerate(hats):
            hat.x.array[cells[:, s]] = 1.0
        return hats

    def _cell_dg_dofs(self):
        """The (owned cells, 3) W dofs of the cells' DG1 dofs, checked to be owned."""
        wdofs = self.systems.W.sub(1).dofmap.list.array.reshape(-1, 3)[:self.cells.shape[0]]
        owned = not wdofs.size or wdofs.max() < self.systems.W.dofmap.index_map.size_local
        if not self.comm.allreduce(bool(owned), op=MPI.LAND):
            raise RuntimeError("a DG1 dof of an owned cell is not owned")
        return wdofs

    def dg_dofs(self, c):
        """The W dofs (cells touching colour c, 3) of the DG1 dofs of the cells touching
        colour c, where the colour's `Load.values` go. Collective at the first call."""
        if self._dg_dofs is None:
            wdofs = self._cell_dg_dofs()
            self._dg_dofs = [wdofs[touching] for touching, _ in self.touching()]
        return self._dg_dofs[c]

    def set_colour(self, c, lam=None):
        """ψ = indicator of colour c at the P1 dofs (owned and ghost); Λ = λ there."""
        mask = self.colour == c
        self._nodal[:, PSI] = mask
        if lam is not None:
            self._nodal[:, LAMC] = np.where(mask, lam, 0.0)

    def loads(self, fs, measures=None, moments=False):
        """The `Load`s of the expressions f_α in `fs`, in one assembly (data measures:
        `measures`, else the constructor's, else dx); with `moments`, also the cells' DG1
        loads of the fs (`assemble_loads`)."""
        measures = measures if measures is not None else self.measures
        measures = measures if measures is not None else [ufl.dx(domain=self.mesh)]
        loads, cell_moments = assemble_loads(self, list(fs), measures)
        return (loads, cell_moments) if moments else loads

    def load(self, f, measures=None):
        """The `Load` of the expression f_α (`loads`)."""
        return self.loads([f], measures)[0]

    def use_data_measures(self, measures):
        """Integrate the loads of later calls with `measures` (the data measures of another
        problem on this mesh: a kept set-up, membranes.app.setups). The Loads made with the
        old measures are dropped: the compatibility of the interior patches needs the rule
        that assembled the new problem's F_α (module notes)."""
        self.measures = measures
        self._loads.clear()

    def _copy(self, target, source):
        n = target.function_space.dofmap.index_map.size_local
        target.x.array[:n] = source.x.array[:n]
        target.x.scatter_forward()

    def sigma(self, alpha, u, lam, r, f, mu, out=None):
        """σ_α,disc (§5) as an RT_1 Function (written into `out` if given)."""
        from dolfinx import fem
        from dolfinx.fem.petsc import assemble_vector
        if alpha not in (1, 2):
            raise ValueError(f"alpha must be 1 or 2, got {alpha!r}")
        if not isinstance(f, Load):
            key = id(f)
            if key not in self._loads:
                self._loads[key] = self.load(f)  # Load.f keeps f alive: the id stays unique
            f = self._loads[key]
        self.sign.value = 1.0 if alpha == 1 else -1.0
        self.mu.value = float(mu)
        n = self.V.dofmap.index_map.size_local
        self._nodal[:n, U] = u.x.array[:n]
        self.nodal.x.scatter_forward()
        self._copy(self.r, r)
        self._copy(self.lam, lam)
        sigma = out if out is not None else fem.Function(self.rt_space)
        systems = self.systems
        if self._home is None:                    # kept until `release`
            self._home = systems.home_vector()
        home = self._home                         # (each colour's gather overwrites its part)
        x = self.x
        x.set(0.0)
        # the scale of the divergence check (`divergence`): the largest right-hand side entry,
        # and μ max|u|, the round-off unit of the moments (μ ∇u·∇ψ, q), which cancel in the sum
        # (large where u is far from 0: u = g = 1e3 on the boundary)
        scale = float(mu) * float(np.abs(self._nodal[:n, U]).max(initial=0.0))
        for c in range(self.ncolours):
            self.set_colour(c, self.lam.x.array)
            with self.b.localForm() as local:
                local.set(0.0)
            assemble_vector(self.b, self.rhs_forms[c])
            self.b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            self._add_data(self.b.array, self.dg_dofs(c), f, c)
            scale = max(scale, largest(self.b))
            # the colour's patches solved in the home vector of one colour; their solutions
            # add up in x, whose RT part is σ_α,disc
            systems.gather(c, self.b, home)
            systems.scatter(c, systems.solve_home(c, home), x, add=True)
        sigma.x.array[:] = 0.0
        systems.add_flux(x, sigma)
        sigma.x.scatter_forward()
        self.defect = self._check(sigma, f, scale)
        return sigma

    def _check(self, sigma, f, scale):
        """The divergence identity of σ_α,disc (`divergence`): the moments (∇·σ ∓ λ + r, q)
        for q in DG1, assembled into the first entries of b's local array (b is free once the
        solutions are added up; W holds DG1 on the same cells, so it has the room), the
        loads' data parts -(f, q) added; their largest entry against `scale`. Returns the
        relative defect; raises if the identity fails. A DG1 dof belongs to one cell, so its
        moment is whole on the process that integrates that cell (its owner): no exchange,
        and the largest entry is taken over all local entries. The defect's squared L² norm
        goes into `defect_sq`: the estimators count it in the bound (their module notes)."""
        Q = self.r.function_space
        imap = Q.dofmap.index_map
        size = imap.size_local + imap.num_ghosts
        with self.b.localForm() as local:
            if local.array.size < size:
                raise RuntimeError("W has fewer local dofs than its DG1 part")
            moments = local.array[:size]
            assemble(equilibration_forms.disc_divergence(sigma, self.sign, self.lam, self.r,
                                                         ufl.TestFunction(Q)),
                     self.mesh, moments)
            cells = Q.dofmap.list.array.reshape(-1, 3)
            for c, (touching, _) in enumerate(self.touching()):
                self._add_data(moments, cells.take(touching, axis=0), f, c)
            defect = largest(moments)
            if self.area is None:
                self.area = triangle_areas(cell_vertices(self.mesh))
            self.defect_sq = norm_squared(moments[cells[:self.area.size]], self.area,
                                          self.comm)
        return check(defect, scale, self.comm, "σ_disc (§5)", mesh=self.mesh)

    @staticmethod
    def _add_data(into, dofs, f, c):
        """into[dofs] += the data part of colour c's right-hand sides (the `Load` f), dofs
        the DG1 dofs (cells touching c, 3) of the space `into` (a numpy array) belongs to. By
        PETSc's VecSetValues on a sequential Vec over `into`: one pass, where numpy's
        into[dofs] += … gathers, adds and scatters."""
        vec = local_vec(into)
        vec.setValues(dofs, f.values[c], addv=PETSc.InsertMode.ADD_VALUES)
        vec.destroy()

    def release(self):
        """Free the work vectors of `sigma` (the home vector and the W vectors b and x; made
        again at the next call): a caller that computes σ for both membranes at once releases
        them after the pair, so that they are not alive under what follows (the estimators'
        cell integrals)."""
        self._home = None
        for v in (self._b, self._x):
            if v is not None:
                v.destroy()
        self._b = self._x = None

    def destroy(self):
        """Free the factorisations and PETSc vectors (the object is unusable afterwards)."""
        self.systems.destroy()
        self.release()

    def summary(self):
        """Global facts of the set-up: colours, Jones–Plassmann rounds, unknowns per colour,
        sharing of the patch inverses (`PatchSystems.stats`)."""
        return dict(colours=self.ncolours, rounds=self.colour_rounds,
                    unknowns=self.systems.sizes(), sharing=self.systems.stats(),
                    vertices=self.V.dofmap.index_map.size_global,
                    processes=self.comm.size)

