"""A folder for the front of PYTHONPATH whose `sitecustomize` makes one package unimportable in
the Python processes started with it: how the tests show what the product does where a user's
environment lacks an optional package (pyvista, matplotlib)."""

import os


def blocking_folder(tmp_path, package):
    """tmp_path/block, holding a sitecustomize.py under which importing `package` raises
    ImportError('no PACKAGE here')."""
    block = tmp_path / "block"
    block.mkdir()
    (block / "sitecustomize.py").write_text(
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name.split('.')[0] == {package!r}:\n"
        f"            raise ImportError('no {package} here')\n"
        "sys.meta_path.insert(0, Block())\n")
    return block


def with_folder_first(folder, pythonpath=None):
    """PYTHONPATH (this process's unless given) with `folder` in front."""
    pythonpath = os.environ.get("PYTHONPATH", "") if pythonpath is None else pythonpath
    return os.pathsep.join([str(folder)] + [p for p in pythonpath.split(os.pathsep) if p])
