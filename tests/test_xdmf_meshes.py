"""XDMF files as user meshes (membranes.fem.mesh_files.read_xdmf, §12): read by dolfinx on
rank 0, checked as every mesh is, refused in one line when they cannot be used."""

import os
import shutil

import numpy as np
import pytest
from mpi4py import MPI

from membranes import scenes, solve
from membranes.model import mesh_headers

from .conftest import cli_bad_input, mpirun
from .test_user_meshes import _dolfinx_mesh, _grid, msh22, same_on_three_processes

DATA = {"f1": "-1 + x", "f2": "0.5", "mu2": 3.0, "levels": 1}


def written(path, nodes, cells):
    """The triangles `cells` on `nodes` written by dolfinx's XDMFFile (path.xdmf, path.h5)."""
    from dolfinx.io import XDMFFile
    with XDMFFile(MPI.COMM_SELF, str(path), "w") as f:
        f.write_mesh(_dolfinx_mesh(nodes, cells, MPI.COMM_SELF))
    return str(path)


def inline(path, nodes, cells, topology="Triangle", grids=None):
    """An XDMF file with its data in the XML (as meshio writes with data_format='XML'): the
    grid 'Grid' of `cells` on `nodes` (2 or 3 coordinates), or the grids `grids` as
    (name, topology, nodes, cells); beside it an HDF5 file of its name (dolfinx 0.5.2 opens
    one), here the one dolfinx writes for a single triangle."""
    def numbers(a):
        return "\n".join(" ".join(repr(v) for v in row) for row in np.asarray(a).tolist())

    grids = grids or [("Grid", topology, nodes, cells)]
    text = ['<?xml version="1.0"?>', '<Xdmf Version="3.0">', "<Domain>"]
    for name, kind, x, c in grids:
        x, c = np.asarray(x, dtype=float), np.asarray(c, dtype=np.int64)
        text += [f'<Grid Name="{name}" GridType="Uniform">',
                 f'<Topology TopologyType="{kind}" NumberOfElements="{len(c)}">',
                 f'<DataItem Dimensions="{c.shape[0]} {c.shape[1]}" NumberType="Int" '
                 f'Format="XML">', numbers(c), "</DataItem>", "</Topology>",
                 f'<Geometry GeometryType="{"XYZ" if x.shape[1] == 3 else "XY"}">',
                 f'<DataItem Dimensions="{x.shape[0]} {x.shape[1]}" Format="XML">',
                 numbers(x), "</DataItem>", "</Geometry>", "</Grid>"]
    text += ["</Domain>", "</Xdmf>"]
    written(path, [(0, 0), (1, 0), (0, 1)], [(0, 1, 2)])
    with open(path, "w") as f:
        f.write("\n".join(text) + "\n")
    return str(path)


def test_an_xdmf_file_is_a_user_mesh(tmp_path):
    """The same triangles as a .msh file, as dolfinx's XDMF file (HDF5 data) and as an XDMF
    file with its data in the XML and three coordinates in the plane z = 0.5, give the .msh
    file's solution (exact Newton, MUMPS: the nodes in other orders, η to round-off, asserted
    1e-10) on hierarchies of the same size; the size check reads the node count from the
    XML."""
    nodes, cells = _grid(6)
    reference = solve(scenes.user(mesh=msh22(tmp_path / "grid.msh", nodes, cells), **DATA),
                      newton="exact", solver="direct")
    raised = np.hstack([nodes, np.full((len(nodes), 1), 0.5)])
    for path in (written(tmp_path / "grid.xdmf", nodes, cells),
                 inline(tmp_path / "plane.xdmf", raised, cells)):
        assert mesh_headers.mesh_file_vertices(path) == 49
        problem = scenes.user(mesh=path, **DATA)
        assert problem.domain == path and problem.description.startswith(f"mesh {path}, ")
        sol = solve(problem, newton="exact", solver="direct")
        assert sol.per_level[-1]["n_vertices"] == reference.per_level[-1]["n_vertices"] == 169
        assert sol.estimates["eta"] == pytest.approx(reference.estimates["eta"], rel=1e-10)


def _renamed_dataset(path):
    written(path, *_grid(2))
    text = open(path).read().replace("/Mesh/mesh/topology", "/Mesh/mesh/elsewhere")
    open(path, "w").write(text)
    return str(path)


def _without_h5(path):
    written(path, *_grid(2))
    os.remove(os.path.splitext(path)[0] + ".h5")
    return str(path)


def _quads(path):
    from dolfinx.io import XDMFFile
    from dolfinx.mesh import CellType, create_unit_square
    with XDMFFile(MPI.COMM_SELF, str(path), "w") as f:
        f.write_mesh(create_unit_square(MPI.COMM_SELF, 2, 2, CellType.quadrilateral))
    return str(path)


def _two_meshes(path):
    nodes, cells = _grid(2)
    return inline(path, None, None, grids=[("a", "Triangle", nodes, cells),
                                           ("b", "Triangle", nodes + 2.0, cells)])


def _unjoined(path):
    left, cells = _grid(2)
    right, _ = _grid(2, shift=(1.0, 0.0))
    return inline(path, np.vstack([left, right]), np.vstack([cells, cells + len(left)]))


def _edited(text, old, new):
    def build(path):
        written(path, *_grid(2))
        with open(path) as f:
            content = f.read()
        with open(path, "w") as f:
            f.write(content.replace(old, new) if old else text)
        return str(path)
    return build


def _elsewhere(path):
    """The grid's data in other.h5 (named so in the XML), and grid.h5 beside it: a copy of
    another mesh's file, of the same shapes."""
    written(path, *_grid(2))
    shutil.copy(os.path.splitext(path)[0] + ".h5", path.parent / "other.h5")
    written(path.parent / "moved.xdmf", _grid(2)[0] * 3.0, _grid(2)[1])
    shutil.copy(path.parent / "moved.h5", os.path.splitext(path)[0] + ".h5")
    # (the same size and times as other.h5: only their bytes tell the two apart)
    times = os.stat(path.parent / "other.h5")
    os.utime(os.path.splitext(path)[0] + ".h5", ns=(times.st_atime_ns, times.st_mtime_ns))
    text = open(path).read().replace("grid.h5:", "other.h5:")
    open(path, "w").write(text)
    return str(path)


def _two_of_one_name(path):
    """A grid of three quadrilaterals and one of triangles, both named 'mesh': the triangles
    were checked and dolfinx read the first grid of the name, the quadrilaterals' numbers
    three at a time (a mesh of 8 vertices on [0, 3] x [0, 1], without a word)."""
    nodes, cells = _grid(2)
    quad_nodes = [(i, j) for j in (0, 1) for i in range(4)]
    quads = [(i, i + 1, i + 5, i + 4) for i in range(3)]
    return inline(path, None, None, grids=[("mesh", "Quadrilateral", quad_nodes, quads),
                                           ("mesh", "Triangle", nodes, cells)])


NODES, CELLS = _grid(2)
BAD = {
    "no HDF5 file": (_without_h5, r"has no HDF5 file '.*grid\.h5' beside it"),
    "a dataset it does not have": (_renamed_dataset, r"^cannot read mesh file '.*': Failed to "
                                                     r"open HDF5 dataset by name$"),
    "quadrilaterals": (_quads, r"is not a linear triangular mesh \(cells: Quadrilateral\)"),
    "quadratic triangles": (lambda p: inline(p, NODES, np.hstack([CELLS, CELLS]),
                                             "Triangle_6"),
                            r"is not a linear triangular mesh \(cells: Triangle_6\)"),
    "mixed cells": (lambda p: inline(p, NODES, CELLS, "Mixed"),
                    r"is not a linear triangular mesh \(cells: Mixed\)"),
    "a tilted plane": (lambda p: inline(p, np.hstack([NODES, NODES[:, :1]]), CELLS),
                       r"is 3D \(its triangles' nodes have z from 0 to 1, a spread of 1 "
                       r"over an extent of 1 in the plane: not one plane z = const\)"),
    "a cell on a node not listed": (lambda p: inline(p, NODES, np.vstack([CELLS, [(0, 1, 9)]])),
                                    r"has cells on nodes it does not list \(node 9 of 9 "
                                    r"nodes\)"),
    # (-1 was taken as the last node by numpy's indexing)
    "a negative node": (lambda p: inline(p, NODES, np.where(CELLS == 8, -1, CELLS)),
                        r"has cells on nodes it does not list \(node -1 of 9 nodes\)"),
    "two grids of one name": (_two_of_one_name, r"has 2 grids named 'mesh': dolfinx reads a "
                                                r"grid by its name, give each its own$"),
    "a NaN coordinate": (lambda p: inline(p, np.where(np.arange(9)[:, None] == 4, np.nan,
                                                      NODES), CELLS),
                         "has non-finite node coordinates"),
    "two meshes": (_two_meshes, r"has 2 meshes \(grids 'a', 'b'\): give a file of one mesh"),
    "no grid": (_edited('<?xml version="1.0"?><Xdmf><Domain/></Xdmf>', None, None),
                r"has no mesh \(no Grid with a Topology in its Domain\)"),
    "broken XML": (_edited('<?xml version="1.0"?><Xdmf><Domain>', None, None),
                   r"is not an XDMF file \(XML: "),
    "another XML file": (_edited('<?xml version="1.0"?><svg/>', None, None),
                         r"is not an XDMF file \(no Xdmf/Domain element\)"),
    "surfaces not joined": (_unjoined, r"is not conforming: 6 boundary node\(s\).* \(its cells "
                                       r"must share their nodes where they meet\)$"),
    "no cells": (lambda p: inline(p, NODES, np.zeros((0, 3), dtype=np.int64)),
                 r"has no cells"),
    # dolfinx's create_mesh corrupted memory (free(): invalid next size) or raised a
    # traceback on these; the checks now run before it
    "a cell twice": (lambda p: inline(p, NODES, np.vstack([CELLS, CELLS[1:2, ::-1]])),
                     r"lists 1 triangle\(s\) twice"),
    "a cell with a repeated node": (lambda p: inline(p, NODES, np.vstack([CELLS, [(0, 0, 4)]])),
                                    r"has 1 degenerate triangle\(s\)"),
    "more cells than nodes can carry": (
        lambda p: inline(p, NODES, np.zeros((19, 3), dtype=np.int64)),
        r"declares 19 cells on 9 nodes, more than a triangulation of 9 nodes can have"),
    # the tolerance of the plane was relative to |z|: this was solved on its projection
    "a tilted plane far from z = 0": (
        lambda p: inline(p, np.hstack([NODES, 1e12 + 0.4 * NODES[:, :1]]), CELLS),
        r"is 3D \(its triangles' nodes have z from 1e\+12 to 1e\+12, a spread of 0\.4 "
        r"over an extent of 1 in the plane"),
    "HDF5 data without its file's name": (
        _edited(None, "grid.h5:/Mesh/mesh/geometry", "/Mesh/mesh/geometry"),
        r"names its Geometry's HDF5 data '/Mesh/mesh/geometry', not as 'file.h5:/dataset'"),
    # Dimensions="18" for 6 triangles is legal XDMF: dolfinx died of a SIGFPE (exit 59)
    "a flat topology": (_edited(None, 'Dimensions="8 3"', 'Dimensions="24"'),
                        r"gives its triangles' Topology Dimensions '24', not 'cells 3'"),
    # dolfinx reads grid.h5 whatever the XML names: this square's data were read from it
    "its data in another .h5 file": (_elsewhere, r"holds its Topology's data in '.*other\.h5', "
                                                 r"but dolfinx 0.5 reads it from '.*grid\.h5'"),
    "a grid without a Name": (_edited(None, ' Name="mesh"', ""),
                              r"has a grid without a Name \(dolfinx reads a grid by its name"),
    "an encoding Python does not know": (
        _edited('<?xml version="1.0" encoding="bogus"?><Xdmf/>', None, None),
        r"is not an XDMF file \(XML: unknown encoding"),
    "XDMF 2's Type attribute": (
        _edited(None, 'TopologyType="Triangle"', 'Type="Triangle"'),
        r"is not a linear triangular mesh \(cells: no TopologyType given\)"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_xdmf_files(case, tmp_path, capfd):
    """Each is refused with one line naming the file and what is wrong with it, before any
    run; HDF5's own error stack is not printed (stderr, file descriptor 2, stays empty)."""
    build, message = BAD[case]
    path = build(tmp_path / "grid.xdmf")
    capfd.readouterr()
    with pytest.raises(ValueError, match=message) as error:
        scenes.user(mesh=path)
    assert "\n" not in str(error.value) and "grid.xdmf" in str(error.value)
    assert capfd.readouterr().err == ""


def test_a_bad_xdmf_file_on_the_command_line(tmp_path, capsys):
    """The command line: exit code 2, one line naming the file, nothing written."""
    err = cli_bad_input(["--mesh", _renamed_dataset(tmp_path / "grid.xdmf")],
                        tmp_path / "out", capsys)
    assert "cannot read mesh file" in err and "grid.xdmf" in err


def test_an_xdmf_file_is_size_checked_before_it_is_read(tmp_path, monkeypatch):
    """--max-vertices against the node count the XML declares, before dolfinx reads the file
    (the reader is replaced by one that fails the test), then exactly once it is read."""
    from membranes.fem import mesh_files
    path = written(tmp_path / "grid.xdmf", *_grid(6))
    real = mesh_files.read_xdmf

    def never(*args, **kwargs):
        raise AssertionError("the file was read")
    monkeypatch.setattr(mesh_files, "read_xdmf", never)
    with pytest.raises(ValueError, match="more than the limit --max-vertices 100 "):
        scenes.user(mesh=path, levels=2, max_vertices=100)
    monkeypatch.setattr(mesh_files, "read_xdmf", real)
    assert scenes.user(mesh=path, levels=1, max_vertices=169).mesh.topology.index_map(
        0).size_global == 169
    with pytest.raises(ValueError, match="more than the limit --max-vertices 168 "):
        scenes.user(mesh=path, levels=1, max_vertices=168)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_an_xdmf_file_on_three_processes(tmp_path):
    """On 3 processes (rank 0 reads, dolfinx distributes) an L-shaped mesh, in HDF5 and in
    the XML, gives the serial η (exact Newton, MUMPS: round-off, asserted 1e-10)
    with the same Newton steps; a bad file is refused in one line, exit code 2, on every
    process alike."""
    nodes, cells = _grid(4)
    keep = ~np.all(nodes[cells].mean(axis=1) > 0.5, axis=1)
    same_on_three_processes(written(tmp_path / "l.xdmf", nodes, cells[keep]))
    # nodes in a plane z = 0.5, data in the XML: dolfinx gave rank 0 all nodes, and the
    # plane's check took the others' none for z = 0 ("is 3D" on 3 processes only)
    raised = np.hstack([nodes, np.full((len(nodes), 1), 0.5)])
    same_on_three_processes(inline(tmp_path / "plane.xdmf", raised, cells[keep]))
    bad = _renamed_dataset(tmp_path / "bad.xdmf")
    proc = mpirun(["-m", "membranes.app.cli", "solve", "--mesh", bad, "--quiet", "--out",
                   tmp_path / "out"], processes=3, timeout=240)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    ours = [line for line in proc.stderr.splitlines() if line.startswith("membranes")]
    assert ours == [f"membranes: error: cannot read mesh file {bad!r}: Failed to open HDF5 "
                    f"dataset by name"], proc.stderr        # (and mpirun's banner)
    assert "HDF5-DIAG" not in proc.stderr
    assert not (tmp_path / "out").exists()


def test_counts_below_zero_are_no_size(tmp_path):
    """A file declaring a negative node count (a gmsh header, an XDMF Dimensions) has no size
    for the check before reading (a complex power of it ended in a TypeError traceback in
    the memory estimate of the direct solver); the reader then says what is wrong."""
    nodes, cells = _grid(2)
    msh = msh22(tmp_path / "grid.msh", nodes, cells)
    text = open(msh).read().replace("$Nodes\n9\n", "$Nodes\n-9\n")
    open(msh, "w").write(text)
    xdmf = _edited(None, 'Dimensions="9 2"', 'Dimensions="-9 2"')(tmp_path / "grid.xdmf")
    for path in (msh, xdmf):
        assert mesh_headers.mesh_file_vertices(path) is None
        with pytest.raises(ValueError, match="cannot read mesh file"):
            scenes.user(mesh=path)


def test_a_process_without_stderr_reads_xdmf(tmp_path):
    """With file descriptor 2 closed (`2>&-`), the quiet reads failed on every file ('NoneType'
    object has no attribute 'flush'); there is nothing to hide then, and the file is read."""
    import subprocess
    import sys
    path = written(tmp_path / "grid.xdmf", *_grid(3))
    code = ("from membranes import scenes; "
            f"print(scenes.user(mesh={path!r}).mesh.topology.index_map(0).size_global)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=False,
                          stdout=subprocess.PIPE, text=True, timeout=120,
                          preexec_fn=lambda: os.close(2))
    assert proc.returncode == 0 and proc.stdout.split() == ["16"]


def test_a_pair_copied_to_a_new_name(tmp_path):
    """grid.xdmf and grid.h5 copied to copy.xdmf and copy.h5: the XML still names grid.h5,
    dolfinx reads copy.h5, the same bytes; read as the original."""
    path = written(tmp_path / "grid.xdmf", *_grid(2))
    shutil.copy(path, tmp_path / "copy.xdmf")
    shutil.copy(tmp_path / "grid.h5", tmp_path / "copy.h5")
    assert "grid.h5:" in open(tmp_path / "copy.xdmf").read()
    assert scenes.user(mesh=tmp_path / "copy.xdmf").mesh.topology.index_map(
        0).size_global == 9


def test_a_comment_before_the_xdmf(tmp_path):
    """An XML comment before the root is XDMF still (it was taken for neither kind of file)."""
    path = written(tmp_path / "grid.xdmf", *_grid(2))
    text = open(path).read()
    assert text.startswith("<?xml")          # (an XML declaration can only come first)
    open(path, "w").write("<!-- written by hand -->\n" + text.split("\n", 1)[1])
    assert scenes.user(mesh=path).mesh.topology.index_map(0).size_global == 9


def test_files_dolfinx_and_editors_write_are_read(tmp_path):
    """What a mutation round found no test reading: a dolfinx mesh file with cell tags
    written after the mesh (a second grid, 'mesh_tags', a common dolfinx output), an XDMF
    file beginning with a UTF-8 byte-order mark, a TopologyType written in lower case, and
    a node no triangle uses off the plane of the others (it is no part of the mesh, as in a
    .msh file)."""
    from dolfinx.io import XDMFFile
    from dolfinx.mesh import meshtags
    mesh = _dolfinx_mesh(NODES, CELLS, MPI.COMM_SELF)
    with XDMFFile(MPI.COMM_SELF, str(tmp_path / "tags.xdmf"), "w") as f:
        f.write_mesh(mesh)
        cells = np.arange(mesh.topology.index_map(2).size_local, dtype=np.int32)
        f.write_meshtags(meshtags(mesh, 2, cells, np.ones_like(cells)))
    assert open(tmp_path / "tags.xdmf").read().count("<Grid ") == 2
    bom = written(tmp_path / "bom.xdmf", NODES, CELLS)
    text = open(bom, "rb").read()
    open(bom, "wb").write(b"\xef\xbb\xbf" + text)
    lower = inline(tmp_path / "lower.xdmf", NODES, CELLS, topology="triangle")
    unused = inline(tmp_path / "unused.xdmf", np.vstack([np.c_[NODES, np.zeros(9)],
                                                         [(0.5, 0.5, 3.0)]]), CELLS)
    for path in (tmp_path / "tags.xdmf", bom, lower, unused):
        mesh = scenes.user(mesh=path).mesh
        assert mesh.topology.index_map(0).size_global == 9, path
        assert mesh.topology.index_map(2).size_global == 8, path
