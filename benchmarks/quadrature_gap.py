"""The data quadrature's gap in the guaranteed bound on the disk (docs/choices.md, §7, §9).

    python benchmarks/quadrature_gap.py [--h 0.2] [--levels 1 2 3 4] [--depth 8]

The oscillation term of §7 needs ∫_K (f_α − Π_P1 f_α) = 0 on every cell K. The product computes
Π_P1 f_α with its data rule (`membranes.fem.quadrature`: degree-6 Gauss, a composite rule on the
cells the circle r = 1/√2 cuts, where the disk's data jump), so its cell means carry the rule's
error δ_K = ∫_K f_α − Q_K(f_α). The term this leaves out of the proof, Σ_K δ_K v̄_K, is at most

    C_PF (Σ_α μ_α⁻¹ Σ_K δ_K² / |K|)^{1/2}

in the energy norm (Cauchy–Schwarz and Poincaré–Friedrichs on Ω). The term itself is the norm
of the functional ℓ(v) = Σ_α Σ_K δ_K v̄_K in the dual of the energy norm, which this script
approximates from below by its Galerkin value on P2 of the same mesh (`dual_norm_squared`).
For the disk scene at each level J both are printed beside η of a default `solve` on the
same hierarchy (nested iteration up to T_J) and its effectivity, and their ratios to η.

Independent of the product's rule: Q_K(f_α) is the product's (one assembly of f_α w dx over its
data measures, w ∈ DG0); ∫_K f_α is computed here from the formulas of §9 (docs/theory.md) coded in
numpy, by splitting each cut cell into four `--depth` times where the circle crosses it
(a sub-triangle lies wholly inside the disk when its three corners do, wholly outside when its
nearest point is farther than 1/√2 from the centre) and cutting the last ones along the chord
through the circle's crossings of their edges; every piece gets a degree-10 Gauss rule with
the formula of its side. The chord's error is of the order of the piece's size cubed.
On the cells the product does not mark as cut both integrals are Gauss rules of a smooth
function, and their largest relative difference is printed as a check of the formulas.

Serial only (the cut cells are gathered from one process). Nothing is asserted.
"""

import argparse
import math
import sys

import numpy as np

G = 0.05                                     # the disk scene's g (§9)
C = G * math.sqrt(2.0) / (math.sqrt(2.0) - 1.0)
R2 = 0.5                                     # the interface r² = 1/2


def data(p, alpha, inside):
    """f_α of §9 at the points p (..., 2), on the side `inside` of the circle (extended)."""
    if alpha == 1:
        return np.full(p.shape[:-1], -10 * G if inside else -8 * G)
    if inside:
        return np.full(p.shape[:-1], -6 * G)
    r = np.sqrt((p ** 2).sum(axis=-1))
    return -C * (1 + 8 * r - 18 * r ** 2) / r


def gauss(degree=10):
    import basix
    return basix.make_quadrature(basix.CellType.triangle, degree)


def integrate(tris, alpha, inside, rule):
    """Σ over the triangles (n, 3, 2) of ∫ f_α (side `inside`), per triangle."""
    from membranes.fem.meshes import triangle_areas
    points, weights = rule
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    x = a[:, None] + points[None, :, :1] * (b - a)[:, None] + points[None, :, 1:] * (c - a)[:, None]
    return 2 * triangle_areas(tris) * (data(x, alpha, inside) @ weights)


def distance_to_origin(tris):
    """The distance from the origin to each triangle (n, 3, 2) (0 where it holds the origin)."""
    d = np.full(len(tris), np.inf)
    for i in range(3):
        a, b = tris[:, i], tris[:, (i + 1) % 3]
        e = b - a
        t = np.clip(-(a * e).sum(axis=1) / (e * e).sum(axis=1), 0.0, 1.0)
        d = np.minimum(d, np.linalg.norm(a + t[:, None] * e, axis=1))
    cross = [np.cross(tris[:, (i + 1) % 3] - tris[:, i], -tris[:, i]) for i in range(3)]
    holds = np.all(np.stack(cross) >= 0, axis=0) | np.all(np.stack(cross) <= 0, axis=0)
    return np.where(holds, 0.0, d)


def children(tris):
    """The four children of each triangle by its edge midpoints, (4n, 3, 2)."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
    return np.concatenate([np.stack(t, axis=1) for t in
                           ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def chord_pieces(tris):
    """Each triangle cut along the chord through the circle's crossings of its edges, where
    r² − 1/2, linear along the edge, is zero: (inside pieces, their owners, outside pieces,
    their owners). A triangle whose corners all lie on one side (the arc crosses one edge
    twice, within the sagitta) goes whole to that side."""
    phi = (tris ** 2).sum(axis=2) - R2                                   # (n, 3)
    inside = phi <= 0
    count = inside.sum(axis=1)
    owners = np.arange(len(tris))
    pieces = {True: [tris[count == 3]], False: [tris[count == 0]]}
    index = {True: [owners[count == 3]], False: [owners[count == 0]]}
    split = (count == 1) | (count == 2)
    t, f, own, lone_in = tris[split], phi[split], owners[split], count[split] == 1
    # the corner alone on its side first (rolled, keeping the orientation)
    lone = np.where(lone_in, np.argmax(inside[split], axis=1), np.argmin(inside[split], axis=1))
    order = (lone[:, None] + np.arange(3)) % 3
    t = np.take_along_axis(t, order[:, :, None], axis=1)
    f = np.take_along_axis(f, order, axis=1)
    v0, v1, v2 = t[:, 0], t[:, 1], t[:, 2]
    x1 = v0 + (f[:, 0] / (f[:, 0] - f[:, 1]))[:, None] * (v1 - v0)
    x2 = v0 + (f[:, 0] / (f[:, 0] - f[:, 2]))[:, None] * (v2 - v0)
    tri = np.stack([v0, x1, x2], axis=1)
    quad = np.concatenate([np.stack([x1, v1, v2], axis=1), np.stack([x1, v2, x2], axis=1)])
    for side in (True, False):
        mine = lone_in if side else ~lone_in                  # the lone corner's side
        pieces[side] += [tri[mine], quad[np.tile(~mine, 2)]]
        index[side] += [own[mine], np.tile(own, 2)[np.tile(~mine, 2)]]
    return (np.concatenate(pieces[True]), np.concatenate(index[True]),
            np.concatenate(pieces[False]), np.concatenate(index[False]))


def accurate_integrals(tris, alpha, depth, rule):
    """∫_K f_α over each triangle (n, 3, 2), the circle resolved as the module notes say."""
    total = np.zeros(len(tris))
    owner = np.arange(len(tris))
    for level in range(depth + 1):
        inside = np.all((tris ** 2).sum(axis=2) <= R2, axis=1)
        outside = ~inside & (distance_to_origin(tris) > math.sqrt(R2))
        for side, which in ((True, inside), (False, outside)):
            np.add.at(total, owner[which], integrate(tris[which], alpha, side, rule))
        cut = ~inside & ~outside
        tris, owner = tris[cut], owner[cut]
        if level < depth:
            tris, owner = children(tris), np.tile(owner, 4)
    pin, oin, pout, oout = chord_pieces(tris)
    np.add.at(total, owner[oin], integrate(pin, alpha, True, rule))
    np.add.at(total, owner[oout], integrate(pout, alpha, False, rule))
    return total


def dual_norm_squared(mesh, W, cell_of, mean, degree=2):
    """‖ℓ‖² of ℓ(v) = Σ_K δ̄_K ∫_K v (δ̄ = `mean` on the cells) in the dual of H¹_0 with
    ‖∇v‖: b·z with A z = b, A the Laplacian on Lagrange elements of `degree` vanishing on ∂Ω
    and b_i = ℓ(φ_i) (CG + BoomerAMG to rtol 1e-10). A Galerkin value: below the dual norm,
    and increasing with the degree."""
    import ufl
    from dolfinx import fem
    from dolfinx.fem import petsc
    from dolfinx.mesh import exterior_facet_indices
    from petsc4py import PETSc
    V = fem.FunctionSpace(mesh, ("Lagrange", degree))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    mesh.topology.create_connectivity(1, 2)
    bc = fem.dirichletbc(0.0, fem.locate_dofs_topological(
        V, 1, exterior_facet_indices(mesh.topology)), V)
    A = petsc.assemble_matrix(fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx), bcs=[bc])
    A.assemble()
    d = fem.Function(W)
    d.x.array[cell_of] = mean
    b = petsc.assemble_vector(fem.form(d * v * ufl.dx))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    petsc.set_bc(b, [bc])
    ksp = PETSc.KSP().create(mesh.comm)
    ksp.setOperators(A)
    ksp.setType("cg")
    ksp.setTolerances(rtol=1e-10)
    ksp.getPC().setType("hypre")
    z = b.duplicate()
    ksp.solve(b, z)
    value = b.dot(z)
    for obj in (ksp, z, b, A):
        obj.destroy()
    return value


def level_gap(j, h0, depth):
    import ufl
    from dolfinx import fem

    from membranes import scenes, solve
    from membranes.fem.discretisation import discretise
    from membranes.fem.meshes import cell_vertices, triangle_areas
    from membranes.fem.quadrature import cut_cells, over
    problem = scenes.disk(h=h0, levels=j).on_level(j)
    disc = discretise(problem)
    mesh = disc.mesh
    nc = mesh.topology.index_map(2).size_local
    W = fem.FunctionSpace(mesh, ("DG", 0))
    w = ufl.TestFunction(W)
    cell_of = W.dofmap.list.array[:nc]
    tris = cell_vertices(mesh)
    area = triangle_areas(tris)
    cut = cut_cells(mesh, problem.interface)
    smooth = np.setdiff1d(np.arange(nc), cut)
    rule = gauss()
    total, check, dual = 0.0, 0.0, 0.0
    for alpha, (f, mu) in enumerate(((disc.f1, problem.mu1), (disc.f2, problem.mu2)), start=1):
        product = fem.assemble_vector(fem.form(over(disc.dx_data, lambda dx: f * w * dx)))
        product = product.array[cell_of]                          # Q_K(f_α) per cell
        mine = accurate_integrals(tris[cut], alpha, depth, rule)
        total += ((mine - product[cut]) ** 2 / area[cut]).sum() / mu
        mean = np.zeros(nc)
        mean[cut] = (mine - product[cut]) / area[cut]
        dual += dual_norm_squared(mesh, W, cell_of, mean) / mu
        sample = smooth[::max(1, smooth.size // 2000)]
        on_side = (tris[sample].mean(axis=1) ** 2).sum(axis=1) <= R2   # (wholly on one)
        plain = np.where(on_side, integrate(tris[sample], alpha, True, rule),
                         integrate(tris[sample], alpha, False, rule))
        check = max(check, float(np.max(np.abs(plain - product[sample]) / np.abs(plain))))
    gap = problem.poincare_constant() * math.sqrt(total)
    summary = solve(problem).summary()                           # (the defaults)
    eta, effectivity = summary["eta"], summary["effectivity"]
    return (mesh.topology.index_map(0).size_global, cut.size, gap, math.sqrt(dual), eta,
            effectivity, check)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=float, default=0.2, help="the coarse mesh size (0.2)")
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 2, 3, 4], metavar="J")
    parser.add_argument("--depth", type=int, default=8,
                        help="halvings of the cut cells before the chord (8)")
    args = parser.parse_args(argv)
    if not args.h > 0 or min(args.levels) < 0 or args.depth < 0:
        parser.error("--h must be positive, the levels and --depth non-negative")
    from mpi4py import MPI
    if MPI.COMM_WORLD.size > 1:
        parser.error("serial only")
    from membranes.app.logs import quiet_jit_logging
    quiet_jit_logging()
    print("| J | vertices | cut cells | C_PF ‖δ̄‖ | ‖ℓ‖ on P2 | η | effectivity | crude / η | "
          "‖ℓ‖ / η | check on uncut cells |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for j in args.levels:
        n, ncut, gap, dual, eta, effectivity, check = level_gap(j, args.h, args.depth)
        print(f"| {j} | {n:,} | {ncut:,} | {gap:.3e} | {dual:.3e} | {eta:.4e} | "
              f"{effectivity:.3f} | {100 * gap / eta:.2f} % | {100 * dual / eta:.3f} % | "
              f"{check:.1e} |", flush=True)


if __name__ == "__main__":
    sys.exit(main())
