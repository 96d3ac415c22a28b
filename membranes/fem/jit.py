"""Compiled forms found in the JIT cache once per process.

dolfinx compiles every form and element through FFCx, which keeps the compiled modules in
one cache directory (``~/.cache/fenics``, shared by every FEniCS program of the user). At each
lookup FFCx's `get_cached_module` makes a new importlib finder and lists that whole directory
again, so each `dolfinx.fem.form` and each function space costs time in proportion to the
number of files in the cache (four per compiled module), however often the same form was
found before; a solve makes some fifty lookups. `cached_module` below keeps one finder per
cache directory, which lists the directory again only when it has changed (a module compiled
meanwhile, by this process or another), and the modules it has loaded, which are found again
without any listing. Whatever is not yet compiled and ready goes through FFCx's own function
unchanged (it creates the C file, compiles, or waits for another process to finish), so the
cache's protocol between processes stays FFCx's.
"""

import importlib.machinery
import importlib.util
import os

_loaded = {}       # (cache directory, module name) -> module
_finders = {}      # cache directory -> importlib FileFinder (lists again when the dir changes)


def _finder(cache_dir):
    finder = _finders.get(cache_dir)
    if finder is None:
        finder = _finders[cache_dir] = importlib.machinery.FileFinder(
            cache_dir, (importlib.machinery.ExtensionFileLoader,
                        importlib.machinery.EXTENSION_SUFFIXES))
    return finder


def cached_module(module_name, object_names, cache_dir, timeout, *, ffcx_lookup):
    """FFCx's `get_cached_module(module_name, object_names, cache_dir, timeout)`, with the
    modules that are ready found by a kept finder and loaded once per process."""
    key = (str(cache_dir), module_name)
    module = _loaded.get(key)
    if module is None:
        if not os.path.exists(os.path.join(key[0], module_name + ".c.cached")):
            return ffcx_lookup(module_name, object_names, cache_dir, timeout)
        spec = _finder(key[0]).find_spec(module_name)
        if spec is None:          # written within the finder's last listing's mtime tick
            return ffcx_lookup(module_name, object_names, cache_dir, timeout)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        _loaded[key] = module
    return [getattr(module.lib, name) for name in object_names], module


def install():
    """Route FFCx's cache lookups through `cached_module` (once; `membranes.fem` does it on
    import, before any form is compiled)."""
    import ffcx.codegeneration.jit as ffcx_jit
    original = ffcx_jit.get_cached_module
    if getattr(original, "membranes", False):
        return

    def get_cached_module(module_name, object_names, cache_dir, timeout):
        return cached_module(module_name, object_names, cache_dir, timeout,
                             ffcx_lookup=original)

    get_cached_module.membranes = True
    ffcx_jit.get_cached_module = get_cached_module
