"""Mesh files as the coarse mesh T_0 (§12): gmsh `.msh` files, read by gmsh, and XDMF files,
read by dolfinx, both on rank 0, as the generated domains are meshed there; dolfinx then
distributes the checked cells (`meshes.on_rank0`). Which reader a file goes to is decided by
its first bytes (`model.mesh_headers.mesh_file_kind`), not by its name, and both end in the
checks every mesh gets (`meshes.checked_cells`): a file that is neither is refused before
any reader sees it (gmsh would run any other text as a `.geo` script, `SystemCall`
included).

**gmsh files** are opened by gmsh and their triangles taken as `meshes.model_cells` says.
gmsh 4.8 crashes on element tags of 2^31 or more, so those are looked for first
(`_element_tags_in_range`).

**XDMF files** are the format dolfinx writes (`dolfinx.io.XDMFFile.write_mesh`) and meshio
writes. The grid that holds the mesh (`mesh_headers.xdmf_grid`: the one with a topology, or
the one of triangles, or the one named 'mesh'; at most 2 cells a node declared, HDF5 data
named 'file.h5:/dataset') is read by dolfinx's XDMFFile on `MPI.COMM_SELF`. dolfinx 0.5.2
opens `name.h5` beside `name.xdmf` whatever the XML names (even where the data are in the
XML), so that file must be there. The cells and nodes are checked before dolfinx's
`create_mesh` sees them (it crashed, or hung, on repeated cells): linear triangles on nodes
the file lists, those nodes with two coordinates, or three in one plane z = c
(`meshes.in_the_plane`, taken as z = 0), then the checks of every mesh. Read on all
processes at once (MPI-IO), a dataset that failed to read on some of them left HDF5 unable
to close the file, and the process aborted; on one process it closes. HDF5 prints its error
stack on stderr: the reads run with the process's stderr sent to /dev/null, and dolfinx's
exception becomes the one-line ValueError.
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
                         f"begins with neither $MeshFormat nor XML)")
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
    with open(path, "rb") as f:
        if not f.read(16).startswith((b"$MeshFormat", b"$NOD")):
            # (gmsh picks its reader by the first bytes: it parsed such a file as a script)
            raise ValueError(f"mesh file {path!r} has blank space or a byte-order mark before "
                             f"its $MeshFormat line, which gmsh cannot read: remove them")
    return meshes.on_rank0(comm, lambda gmsh: _check_msh(gmsh, path))


# ## XDMF files

@contextlib.contextmanager
def _no_stderr():
    """The process's stderr (file descriptor 2, where HDF5 prints its error stack) sent to
    /dev/null, and back after; nothing to do where the process has no stderr."""
    if sys.stderr is not None:
        sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:                       # (fd 2 closed: nothing would be printed)
        saved = None
    try:
        if saved is not None:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 2)
        yield
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)


def _quietly(what, step):
    """step(), with stderr sent to /dev/null; dolfinx's exception as a ValueError."""
    try:
        with _no_stderr():
            return step()
    except Exception as e:
        raise ValueError(f"cannot read {what}: {str(e).strip() or type(e).__name__}") \
            from None


def _closed(xdmf):
    """Close the file, quietly: after a failed read HDF5 may not close it (read on several
    processes it could not: "Failed to close HDF5 file" and its error stack), and the error
    to report is the read's."""
    try:
        with _no_stderr():
            xdmf.close()
    except Exception:
        pass


def read_xdmf(path, comm=MPI.COMM_WORLD):
    """Read the mesh of an XDMF file with dolfinx on rank 0, check it there and distribute it
    on `comm` (module notes); ValueError, the same on every process, names what is wrong.
    Collective."""
    path = check_mesh_path(path)
    return meshes.on_rank0(comm, lambda _: _read_xdmf(path), contextlib.nullcontext)


def _read_xdmf(path):
    """(cells, x) of the XDMF file's mesh, checked: rank 0's part of `read_xdmf`."""
    from dolfinx.io import XDMFFile
    what = f"mesh file {path!r}"
    name, kind, _, _ = xdmf_grid(path)
    # (dolfinx's own reading of the type: "Unknown value: mixed", or worse; "Triangle" is
    # its linear triangle)
    if kind.lower() != "triangle":
        raise ValueError(f"{what} is not a linear triangular mesh (cells: "
                         f"{kind or 'no TopologyType given'})")
    xdmf = _quietly(what, lambda: XDMFFile(MPI.COMM_SELF, path, "r"))
    try:
        cells = _quietly(what, lambda: xdmf.read_topology_data(name, XPATH))
        x = _quietly(what, lambda: xdmf.read_geometry_data(name, XPATH))
    finally:
        _closed(xdmf)
    return _checked(np.asarray(cells), np.asarray(x, dtype=float), what)


def _checked(cells, x, what):
    """(cells, x) of an XDMF file's cells and nodes, on the nodes the cells use, checked as a
    .msh file's (`meshes.checked_cells`) before dolfinx sees them: its create_mesh crashed
    or hung on repeated cells and on cells with a repeated node."""
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"{what} has nodes of other than 2 or 3 coordinates")
    cells = np.reshape(cells, (-1, 3)).astype(np.int64)
    x = np.pad(x, ((0, 0), (0, 3 - x.shape[1])))
    if not len(cells):
        raise ValueError(f"{what} has no cells")
    if cells.min() < 0 or cells.max() >= len(x):
        bad = cells.min() if cells.min() < 0 else cells.max()
        raise ValueError(f"{what} has cells on nodes it does not list (node {bad} of "
                         f"{len(x)} nodes)")
    used, cells = np.unique(cells, return_inverse=True)
    cells = cells.reshape(-1, 3)
    x = meshes.in_the_plane(x[used], what)
    return meshes.checked_cells(x, cells, what, fix=meshes.JOIN_NODES)[:2]


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
    # (the line may end in CR LF: gmsh reads such files, and a search for "$Elements\n"
    # missed their section, so that a tag of 2^31 crashed gmsh and one of 2^32 was wrapped)
    section = re.search(rb"^\$(Elements|ELM)[ \t\r]*$", data, re.M)
    if section is None:
        return                                          # (gmsh says what is missing)
    start = data.find(b"\n", section.end()) + 1

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


