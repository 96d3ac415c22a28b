"""membranes.kept: arrays handed out again only once nothing else refers to them."""

import numpy as np
import pytest

from membranes.kept import KeptArrays


@pytest.mark.parametrize("size", [12, 5 << 20])     # small, and mapped anew by malloc (40 MB)
def test_an_array_is_handed_out_again_only_when_free(size):
    kept = KeptArrays(2)
    a = kept.empty((3, size // 3))
    address = a.ctypes.data
    b = kept.empty((3, size // 3))              # a is held: another one
    assert not np.shares_memory(a, b)
    a[:] = 1.0
    view = a[1]
    del a
    c = kept.empty((3, size // 3))              # a's view holds it: a third, not kept
    assert not np.shares_memory(c, view) and not np.shares_memory(c, b)
    assert np.all(view == 1.0)
    del view, c
    d = kept.empty((3, size // 3))              # a is free now: handed out again
    assert d.ctypes.data == address and len(kept.buffers) == 2


def test_dtype_and_size():
    kept = KeptArrays(1)
    a = kept.empty(10, np.int32)
    address = a.ctypes.data
    del a
    b = kept.empty(10, np.float64)              # another dtype: a new one, kept instead
    assert b.dtype == np.float64 and b.ctypes.data != address
    address = b.ctypes.data
    del b
    c = kept.empty((2, 3))                      # fewer entries: the kept buffer's first ones
    assert c.shape == (2, 3) and c.ctypes.data == address
    del c
    d = kept.empty(11)                          # more: a new one
    assert d.size == 11 and d.ctypes.data != address
