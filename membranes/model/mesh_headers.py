"""What a mesh file declares, read without reading its mesh: the kind of file (a gmsh `.msh`
or an XDMF file, by its first bytes, whatever its name), the node count of a gmsh file's
header, and the grid of an XDMF file that holds the mesh (§12). The size check reads the
counts before any mesh is read (`checks.estimate_vertices`); the readers of `fem.mesh_files`
read the mesh the grid names. Plain Python: nothing here needs dolfinx or gmsh.
"""

import filecmp
import os
import xml.etree.ElementTree as ElementTree

# Bytes of a gmsh file per vertex, a lower bound: gmsh writes 84-100 B per vertex with its
# triangles (a rectangle at h = 0.02 in msh 2.2 and 4.1, ASCII and binary), so a file's size
# over 40 B bounds its vertex count from above where its header cannot be read.
MIN_FILE_BYTES_PER_VERTEX = 40.0


def _msh_vertices(path):
    """The node count a gmsh .msh file declares (formats 2 and 4, ASCII or binary), read from
    its $Nodes header without reading the nodes; its size over MIN_FILE_BYTES_PER_VERTEX
    where the header is not found in the first 64 MiB; None where the path is no readable
    gmsh file (the mesh reader then says what is wrong with it)."""
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            head = f.read(1 << 16)
            # MSH 1, "$NOD\nN\n" and no $MeshFormat (such files had no size check)
            if head.startswith(b"$NOD"):
                return _count(int(head.split(b"\n", 2)[1]))
            if not head.startswith(b"$MeshFormat"):
                return None
            fmt = head.split(b"\n", 2)[1].split()
            version, binary, word = float(fmt[0]), fmt[1] == b"1", int(fmt[2])
            data, at = head, 0
            while b"$Nodes" not in data and at < (1 << 26):
                more = f.read(1 << 20)
                if not more:
                    return None
                at += len(more)
                data = data[-16:] + more
            if b"$Nodes" not in data:
                return size / MIN_FILE_BYTES_PER_VERTEX
            start = data.index(b"$Nodes")
            tail = data[start:] + f.read(256)
    except (OSError, ValueError, IndexError):
        return None
    body = tail.split(b"\n", 1)[1]
    try:
        if version < 4:                            # "$Nodes\nN\n" (ASCII even in binary files)
            return _count(int(body.split(b"\n", 1)[0]))
        if not binary:                             # "blocks nodes min max"
            return _count(int(body.split(b"\n", 1)[0].split()[1]))
        endian = "little" if int.from_bytes(head.split(b"\n", 3)[2][:4], "little") == 1 \
            else "big"
        return _count(int.from_bytes(body[word:2 * word], endian))   # blocks, nodes, ...
    except (ValueError, IndexError):
        return size / MIN_FILE_BYTES_PER_VERTEX


def _count(n):
    """A declared count as a float, None where it is negative (the reader refuses it)."""
    return float(n) if n >= 0 else None


def mesh_file_kind(path):
    """'msh' for a gmsh file (it begins with $MeshFormat, or $NOD in format 1), 'xdmf' for
    an XML file (it begins with <?xml, <!DOCTYPE, a comment or <Xdmf), else None (also where
    it cannot be read)."""
    try:
        with open(path, "rb") as f:
            head = f.read(256).lstrip(b"\xef\xbb\xbf \t\r\n")
    except OSError:
        return None
    if head.startswith((b"$MeshFormat", b"$NOD")):
        return "msh"
    if head.startswith((b"<?xml", b"<!DOCTYPE", b"<!--", b"<Xdmf")):
        return "xdmf"
    return None


def _leading_count(item):
    """The first number of a DataItem's Dimensions ("25 2" -> 25), None if it has none or
    it is negative (dolfinx then refuses the file)."""
    try:
        count = int(item.get("Dimensions", "").split()[0])
    except (AttributeError, IndexError, ValueError):
        return None
    return count if count >= 0 else None


def _same_bytes(a, b):
    """Whether the files a and b hold the same bytes (True where they cannot be read: the
    reader then says so)."""
    try:
        return filecmp.cmp(a, b, shallow=False)
    except OSError:
        return True


def h5_beside(path):
    """`name.h5` of the XDMF file `name.xdmf`: the HDF5 file dolfinx 0.5.2 opens with it."""
    return os.path.splitext(path)[0] + ".h5"


def _hdf_path(path, part, item):
    """ValueError unless the DataItem `item` of the grid's `part` (Topology, Geometry) holds
    data dolfinx 0.5.2 reads as named: XML numbers, or HDF5 data named 'file.h5:/dataset'
    (without the file name it crashed, a segmentation fault) in the file `name.h5` beside
    `name.xdmf`, the one it opens whatever the XML names: another file's data of the same
    shape would be read from the wrong file, without a word. (A copy of the named file, as a
    pair copied to a new name leaves it, is read as well as the file itself.)"""
    if item is None:
        raise ValueError(f"mesh file {path!r} has no DataItem in its {part}")
    if item.get("Format", "XML") == "HDF":
        file, _, dataset = (item.text or "").strip().partition(":")
        if not file or not dataset.startswith("/"):
            raise ValueError(f"mesh file {path!r} names its {part}'s HDF5 data "
                             f"{(item.text or '').strip()!r}, not as 'file.h5:/dataset'")
        named = os.path.join(os.path.dirname(path), file)
        beside = h5_beside(path)
        if os.path.isfile(named) and os.path.isfile(beside) and \
                os.path.realpath(named) != os.path.realpath(beside) and \
                not _same_bytes(named, beside):                    # (a copy of it is fine)
            raise ValueError(f"mesh file {path!r} holds its {part}'s data in {named!r}, but "
                             f"dolfinx 0.5 reads it from {beside!r}, the .h5 file of its "
                             f"name: rename them to one name")


def xdmf_grid(path):
    """(name, cell type, nodes, cells) of the grid of the XDMF file at `path` that holds its
    mesh: the one Grid of its Domain with a Topology, or, of several, the one of triangles, or
    the one named 'mesh' (dolfinx's name); its TopologyType as written, the counts its
    Geometry and Topology DataItems declare (None where absent). ValueError naming what is
    wrong: no XML, no Xdmf/Domain, no grid with a topology, several meshes, no `h5_beside`,
    HDF5 data not named 'file.h5:/dataset', more cells than nodes can carry."""
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, LookupError, ValueError) as e:   # (LookupError: an
        # unknown encoding; ValueError: "multi-byte encodings are not supported")
        raise ValueError(f"mesh file {path!r} is not an XDMF file (XML: {e})") from None
    except OSError as e:
        raise ValueError(f"mesh file {path!r} cannot be read: {e.strerror or e}") from None
    domain = root.find("Domain") if root.tag == "Xdmf" else None
    if domain is None:
        raise ValueError(f"mesh file {path!r} is not an XDMF file (no Xdmf/Domain element)")
    grids = [g for g in domain.findall("Grid") if g.find("Topology") is not None]
    if not grids:
        raise ValueError(f"mesh file {path!r} has no mesh (no Grid with a Topology in its "
                         f"Domain)")

    def kind(grid):         # (XDMF 2's Type= dolfinx does not read: "" then)
        return grid.find("Topology").get("TopologyType", "")

    if len(grids) > 1:
        grids = [g for g in grids if kind(g).lower().startswith("triangle")] or grids
    if len(grids) > 1:
        grids = [g for g in grids if g.get("Name") == "mesh"] or grids
    if len(grids) > 1:
        names = ", ".join(repr(g.get("Name", "")) for g in grids)
        raise ValueError(f"mesh file {path!r} has {len(grids)} meshes (grids {names}): give "
                         f"a file of one mesh, or name 'mesh' the one to use")
    grid = grids[0]
    same = [g for g in domain.findall("Grid") if g.get("Name") == grid.get("Name")]
    if grid.get("Name") is not None and len(same) > 1:
        # (dolfinx reads the first grid of the name, /Xdmf/Domain/Grid[@Name=...]: another
        # mesh than the one checked)
        raise ValueError(f"mesh file {path!r} has {len(same)} grids named "
                         f"{grid.get('Name')!r}: dolfinx reads a grid by its name, give each "
                         f"its own")
    geometry, topology = grid.find("Geometry"), grid.find("Topology")
    if geometry is None:
        raise ValueError(f"mesh file {path!r} has no Geometry in its grid")
    if grid.get("Name") is None:
        raise ValueError(f"mesh file {path!r} has a grid without a Name (dolfinx reads a "
                         f"grid by its name: give it Name=\"mesh\")")
    shape = (topology.find("DataItem").get("Dimensions", "").split()
             if topology.find("DataItem") is not None else [])
    if kind(grid).lower() == "triangle" and (len(shape) != 2 or shape[1] != "3"):
        # (Dimensions="6" for two triangles, legal XDMF: dolfinx died of a SIGFPE)
        raise ValueError(f"mesh file {path!r} gives its triangles' Topology Dimensions "
                         f"{' '.join(shape)!r}, not 'cells 3'")
    if not os.path.isfile(h5_beside(path)):
        raise ValueError(f"mesh file {path!r} has no HDF5 file {h5_beside(path)!r} beside it "
                         f"(dolfinx 0.5 reads an XDMF file with the .h5 file of its name)")
    for part, element in (("Topology", topology), ("Geometry", geometry)):
        _hdf_path(path, part, element.find("DataItem"))
    nodes = _leading_count(geometry.find("DataItem"))
    cells = _leading_count(topology.find("DataItem"))
    if nodes is not None and cells is not None and cells > 2 * nodes:
        # a triangulation of the plane on V nodes has at most 2 V - 5 triangles; dolfinx's
        # create_mesh crashed or hung on such files (many repeated cells on few nodes)
        raise ValueError(f"mesh file {path!r} declares {cells} cells on {nodes} nodes, more "
                         f"than a triangulation of {nodes} nodes can have")
    return grid.get("Name", ""), kind(grid), nodes, cells


def mesh_file_vertices(path):
    """The node count the mesh file at `path` declares (a gmsh file's $Nodes header, an XDMF
    file's Geometry), without reading its nodes; None where the path is no readable mesh file
    of either kind (its reader then says what is wrong with it)."""
    kind = mesh_file_kind(path)
    if kind == "msh":
        return _msh_vertices(path)
    if kind == "xdmf":
        try:
            nodes = xdmf_grid(path)[2]
        except ValueError:
            return None
        return None if nodes is None else float(nodes)
    return None
