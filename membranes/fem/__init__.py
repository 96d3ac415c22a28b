"""Meshes, the hierarchy, the discretisation (theory §2, §12), and the JIT cache lookups of
the compiled forms (`jit`, installed here, before any form is compiled)."""

from . import jit

jit.install()
