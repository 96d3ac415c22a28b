"""Mesh files as the coarse mesh T_0 (§12): gmsh `.msh` files, read by gmsh on rank 0, and
XDMF files, read by dolfinx on every process. Which reader a file goes to is decided by its
first bytes (`model.mesh_headers.mesh_file_kind`), not by its name, and both end in the checks
every mesh gets (`meshes.checked_cells`): a file that is neither is refused before any reader
sees it (gmsh would run any other text as a `.geo` script, `SystemCall` included).

**gmsh files** are opened by gmsh on rank 0 and their triangles taken as `meshes.model_cells`
says; dolfinx distributes them. gmsh 4.8 crashes on element tags of 2^31 or more, so those
are looked for first (`_element_tags_in_range`).

**XDMF files** are the format dolfinx writes (`dolfinx.io.XDMFFile.write_mesh`) and meshio
writes. The grid that holds the mesh (`mesh_headers.xdmf_grid`: the one with a topology, or
the one of triangles, or the one named 'mesh') is read by dolfinx's XDMFFile, each process
its own block of the cells and nodes, so no process reads the whole file. The cells must be
linear triangles; the nodes may have two coordinates, or three in one plane z = c (taken as
z = 0; unlike a gmsh file's, every node listed is looked at, not only those of cells). dolfinx
0.5.2 opens `name.h5` beside `name.xdmf` whatever the XML names (even where the data are in
the XML), so that file must be there. The cells must index the nodes listed (dolfinx would
crash otherwise); dolfinx then distributes them without ghost cells, and the mesh gets the
checks of a dolfinx mesh given through the API (`meshes.given_mesh`, on T_0 gathered on rank
0, as a gmsh file is read there). HDF5 prints its error stack on stderr: the reads run with
the process's stderr sent to /dev/null, and dolfinx's exception, agreed by all processes,
becomes the one-line ValueError.
"""

import contextlib
import os
import sys

import numpy as np
from mpi4py import MPI

from ..model.mesh_headers import mesh_file_kind, xdmf_grid
from . import meshes

XPATH = "/Xdmf/Domain"     # where dolfinx looks for the grid


def check_mesh_path(path):
    """The readable gmsh or XDMF file at `path` (str, bytes or os.PathLike) as a str, or
    ValueError naming what is wrong (no reader needed). Anything else is refused before a file
    is touched: an int would be taken for an open file descriptor of the process, and closed
    after reading."""
    try:
        path = os.fsdecode(path)
    except TypeError:
        raise ValueError(f"mesh must be the path of a .msh or .xdmf file (or a dolfinx "
                         f"Mesh), got {path!r}") from None
    if not os.path.exists(path):
        raise ValueError(f"mesh file {path!r} does not exist")
    if not os.path.isfile(path):
        raise ValueError(f"mesh file {path!r} is not a file")
    if not os.access(path, os.R_OK):
        raise ValueError(f"mesh file {path!r} is not readable")
    try:
        with open(path, "rb"):
            pass
    except OSError as e:
        raise ValueError(f"mesh file {path!r} cannot be read: {e.strerror or e}") from None
    if mesh_file_kind(path) is None:
        raise ValueError(f"mesh file {path!r} is not a gmsh .msh file nor an XDMF file (it "
                         f"begins with neither $MeshFormat nor <?xml)")
    return path


def read_mesh_file(path, comm=MPI.COMM_WORLD):
    """The coarse mesh of the gmsh or XDMF file at `path`, distributed on `comm`; ValueError,
    the same on every process, names what is wrong with it. Collective."""
    path = check_mesh_path(path)
    return read_xdmf(path, comm) if mesh_file_kind(path) == "xdmf" else read_msh(path, comm)


def read_msh(path, comm=MPI.COMM_WORLD):
    """Read a 2D triangular gmsh `.msh` file on rank 0 and distribute it; ValueError names
    what is wrong with it."""
    path = check_mesh_path(path)
    if mesh_file_kind(path) != "msh":
        raise ValueError(f"mesh file {path!r} is not a gmsh .msh file (it does not begin "
                         f"with $MeshFormat)")
    return meshes.on_rank0(comm, lambda gmsh: _check_msh(gmsh, path))


# ## XDMF files

@contextlib.contextmanager
def _no_stderr():
    """The process's stderr (file descriptor 2, where HDF5 prints its error stack) sent to
    /dev/null, and back after."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _agreed(comm, what, step):
    """step() on every process, quietly; ValueError on every process if it failed on any
    (the message of the lowest rank that failed)."""
    try:
        with _no_stderr():
            result, error = step(), None
    except Exception as e:
        result, error = None, str(e).strip() or type(e).__name__
    failed = [e for e in comm.allgather(error) if e is not None]
    if failed:
        raise ValueError(f"cannot read {what}: {failed[0]}")
    return result


def _grid(path, comm):
    """`mesh_headers.xdmf_grid` of the file, read on rank 0, with its HDF5 file beside it
    (module notes); ValueError on every process."""
    grid = None
    if comm.rank == 0:
        try:
            grid = xdmf_grid(path)
            h5 = os.path.splitext(path)[0] + ".h5"
            if not os.path.isfile(h5):
                raise ValueError(f"mesh file {path!r} has no HDF5 file {h5!r} beside it "
                                 f"(dolfinx 0.5 reads an XDMF file with the .h5 file of "
                                 f"its name)")
        except ValueError as e:
            grid = str(e)
    grid = comm.bcast(grid, root=0)
    if isinstance(grid, str):
        raise ValueError(grid)
    return grid


def read_xdmf(path, comm=MPI.COMM_WORLD):
    """Read the mesh of an XDMF file with dolfinx on every process of `comm` and check it
    (module notes); ValueError, the same on every process, names what is wrong. Collective."""
    from dolfinx.io import XDMFFile
    from dolfinx.mesh import CellType
    path = check_mesh_path(path)
    what = f"mesh file {path!r}"
    name, kind, _, _ = _grid(path, comm)
    if kind.lower() != "triangle":              # (dolfinx: "Unknown value: mixed", or worse)
        raise ValueError(f"{what} is not a linear triangular mesh (cells: {kind or 'none'})")
    xdmf = _agreed(comm, what, lambda: XDMFFile(comm, path, "r"))
    try:
        cell, degree = _agreed(comm, what, lambda: xdmf.read_cell_type(name, XPATH))
        if cell != CellType.triangle or degree != 1:
            raise ValueError(f"{what} is not a linear triangular mesh (cells: "
                             f"{kind or cell.name})")
        cells = _agreed(comm, what, lambda: xdmf.read_topology_data(name, XPATH))
        x = _agreed(comm, what, lambda: xdmf.read_geometry_data(name, XPATH))
    finally:
        xdmf.close()
    cells, x = np.asarray(cells, dtype=np.int64).reshape(-1, 3), np.asarray(x, dtype=float)
    nodes = comm.allreduce(len(x), op=MPI.SUM)
    if not comm.allreduce(len(cells), op=MPI.SUM):
        raise ValueError(f"{what} has no cells")
    low = comm.allreduce(cells.min() if cells.size else 0, op=MPI.MIN)
    high = comm.allreduce(cells.max() if cells.size else 0, op=MPI.MAX)
    if low < 0 or high >= nodes:
        bad = low if low < 0 else high
        raise ValueError(f"{what} has cells on nodes it does not list (node {bad} of "
                         f"{nodes} nodes)")
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"{what} has nodes of {x.shape[-1]} coordinates, not 2 or 3")
    if comm.allreduce(int(np.count_nonzero(~np.isfinite(x))), op=MPI.SUM):
        raise ValueError(f"{what} has non-finite node coordinates")
    if x.shape[1] == 3:
        z = x[:, 2] if len(x) else np.zeros(1)
        low, high = comm.allreduce(z.min(), op=MPI.MIN), comm.allreduce(z.max(), op=MPI.MAX)
        scale = comm.allreduce(np.abs(x).max() if len(x) else 0.0, op=MPI.MAX)
        if high - low > 1e-12 * max(1.0, scale):
            raise ValueError(f"{what} is 3D (its nodes have z from {low:g} to {high:g}, not "
                             f"one plane z = const)")
    mesh = meshes.distribute(comm, cells, np.ascontiguousarray(x[:, :2]))
    return meshes.given_mesh(mesh, what)


# ## gmsh files

def _element_tags_in_range(gmsh, path):
    """ValueError if the element section of the .msh file at `path` holds a tag of 2^31 or
    more. gmsh 4.8 crashes on such node tags in MSH 4.x files (a segmentation fault inside
    gmsh.open: 3 of 40 random byte corruptions of a binary file) and wraps those of 2^32 and
    more onto other nodes; no mesh this program can hold has them. Looked at without gmsh:
    the text of an ASCII file, the element blocks of a little-endian binary MSH 4.1 file (an
    int dim, entity and type and a size_t count, then per element its tag and node tags).
    What gmsh reads otherwise (MSH 2.2 binary: C ints) it checks itself."""
    import re
    limit = 1 << 31
    with open(path, "rb") as f:
        data = f.read()
    head = re.match(rb"\s*\$MeshFormat\s+(\S+)\s+(\d)\s+(\d+)[^\n]*\n", data[:256])
    start = max(data.find(b"$Elements\n"), data.find(b"$ELM\n"))
    if start < 0:
        return                                          # (gmsh says what is missing)
    start = data.find(b"\n", start) + 1

    def refuse(tag):
        raise ValueError(f"mesh file {path!r} has a tag of 2^31 or more in its elements "
                         f"({tag}): a corrupt file?")

    if head is None or head.group(2) == b"0":           # ASCII (MSH 1.0 has no header)
        end = data.find(b"$End", start)
        for number in re.finditer(rb"\d{10,}", data[start:end if end > 0 else None]):
            if int(number.group()) >= limit:
                refuse(int(number.group()))
        return
    if head.group(1) != b"4.1" or head.group(3) != b"8" or \
            data[head.end():head.end() + 4] != (1).to_bytes(4, "little"):
        return

    def read(dtype, offset, count=1):
        return np.frombuffer(data, dtype=dtype, count=count, offset=offset)

    at = start + 32                                     # (the section's 4 size_t)
    for _ in range(int(read("<u8", start)[0]) if start + 32 <= len(data) else 0):
        if at + 20 > len(data):
            return                                      # (too short: gmsh refuses it)
        kind, count = int(read("<i4", at + 8)[0]), int(read("<u8", at + 12)[0])
        try:
            width = 1 + int(gmsh.model.mesh.getElementProperties(kind)[3])
        except Exception:
            return                                      # (an unknown type: gmsh refuses it)
        if count > (len(data) - at - 20) // (8 * width):
            return                                      # (too short: gmsh refuses it)
        tags = read("<u8", at + 20, width * count)
        if tags.size and tags.max() >= limit:
            refuse(int(tags.max()))
        at += 20 + 8 * width * count


def _check_msh(gmsh, path):
    _element_tags_in_range(gmsh, path)
    try:
        gmsh.open(path)
    except Exception as e:
        reason = str(e).strip() or "gmsh stopped without saying why"
        raise ValueError(f"cannot read mesh file {path!r}: {reason}") from None
    dim = gmsh.model.getDimension()
    if dim == 3 or gmsh.model.mesh.getElementTypes(3).size:
        raise ValueError(f"mesh file {path!r} is 3D; a 2D triangular mesh is required")
    types = list(gmsh.model.mesh.getElementTypes(2))
    if dim < 2 or not types:
        raise ValueError(f"mesh file {path!r} has no 2D cells")
    if types != [meshes.GMSH_TRIANGLE]:
        names = [gmsh.model.mesh.getElementProperties(t)[0] for t in types]
        raise ValueError(f"mesh file {path!r} is not a linear triangular mesh "
                         f"(cells: {', '.join(names)})")
    return meshes.model_cells(gmsh, f"mesh file {path!r}")


