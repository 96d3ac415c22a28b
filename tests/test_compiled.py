"""membranes.compiled: kernels kept on disk as extension modules per argument types, imported
by a later process without numba."""

import importlib
import os
import subprocess
import sys

import numpy as np

from membranes.compiled import _type_key

KERNEL_MODULE = '''
from membranes.compiled import kernel


@kernel
def scaled_sum(a, s):
    total = 0.0
    for i in range(len(a)):
        total += s * a[i]
    return total
'''


def _kernel_module(tmp_path, write=True):
    if write:
        (tmp_path / "kernel_module.py").write_text(KERNEL_MODULE)
    sys.path.insert(0, str(tmp_path))
    importlib.invalidate_caches()
    try:
        return importlib.import_module("kernel_module")
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("kernel_module", None)


def _kept(tmp_path):
    folder = tmp_path / "__pycache__" / "kernels"
    return sorted(os.listdir(folder)) if folder.exists() else []


def test_kept_module_per_types_and_later_process_without_numba(tmp_path):
    module = _kernel_module(tmp_path)
    a = np.arange(5.0)
    # sums of small integers: exact in floating point
    assert module.scaled_sum(a, 2.0) == module.scaled_sum.py_func(a, 2.0) == 20.0
    assert len(_kept(tmp_path)) == 1
    assert module.scaled_sum(np.arange(5, dtype=np.int32), 3) == 30.0   # other types
    assert module.scaled_sum(a[::2], 1.0) == 6.0                         # layout A
    assert len(_kept(tmp_path)) == 3
    module.scaled_sum(a, 2.0)
    assert len(_kept(tmp_path)) == 3                                     # kept: no rebuild
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import numpy as np; "
            "import kernel_module as m; print(m.scaled_sum(np.arange(5.0), 2.0), "
            "'numba' in sys.modules)")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True,
                         text=True, check=True, env=env).stdout.split()
    assert out == ["20.0", "False"]


def test_arguments_not_plain_run_as_njit(tmp_path):
    module = _kernel_module(tmp_path)
    assert module.scaled_sum((1.0, 2.0, 3.0), 2.0) == 12.0              # a tuple: njit
    assert _kept(tmp_path) == []


def test_type_key_is_numbas_typeof():
    import numba
    a = np.zeros((3, 4))
    r = a.copy()
    r.flags.writeable = False
    values = [a, a.T, a[:, ::2], r, np.zeros(3, dtype=np.int32), np.zeros(3, dtype=bool), 1,
              1.5, True, np.float64(1.0), np.int32(2)]
    keys = [_type_key(v) for v in values]
    types = [numba.typeof(v) for v in values]
    # equal keys exactly where numba's types are equal
    for i in range(len(values)):
        for j in range(len(values)):
            assert (keys[i] == keys[j]) == (types[i] == types[j]), (values[i], values[j])
    assert _type_key((1, 2)) is None and _type_key(None) is None


def test_a_failed_build_is_not_tried_again(tmp_path, monkeypatch):
    import membranes.compiled as compiled
    tries = []

    def failing(f, args, path):
        tries.append(path)
        raise RuntimeError("no C compiler")
    monkeypatch.setattr(compiled, "_build_module", failing)
    a = np.arange(5.0)
    assert _kernel_module(tmp_path).scaled_sum(a, 2.0) == 20.0        # njit instead
    assert len(tries) == 1 and os.path.exists(tries[0] + ".failed")
    again = _kernel_module(tmp_path, write=False)                     # a new module object
    assert again.scaled_sum(a, 2.0) == 20.0
    assert len(tries) == 1                                             # the marker: no retry


def test_an_edited_source_replaces_its_kept_module(tmp_path):
    module = _kernel_module(tmp_path)
    a = np.arange(5.0)
    assert module.scaled_sum(a, 2.0) == 20.0
    before = _kept(tmp_path)
    (tmp_path / "kernel_module.py").write_text(KERNEL_MODULE + "\n# edited\n")
    edited = _kernel_module(tmp_path, write=False)
    assert edited.scaled_sum(a, 2.0) == 20.0
    after = _kept(tmp_path)
    assert len(before) == len(after) == 1 and before != after       # rebuilt, the old one gone
