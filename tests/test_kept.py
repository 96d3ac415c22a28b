"""membranes.kept: arrays handed out again only once nothing else refers to them."""

import numpy as np

from membranes.kept import KeptArrays


def test_an_array_is_handed_out_again_only_when_free():
    kept = KeptArrays(2)
    a = kept.empty((3, 4))
    address = a.ctypes.data
    b = kept.empty((3, 4))                      # a is held: another one
    assert not np.shares_memory(a, b)
    a[:] = 1.0
    view = a[1]
    del a
    c = kept.empty((3, 4))                      # a's view holds it: a third, not kept
    assert c.ctypes.data != address and not np.shares_memory(c, view)
    del view, c
    d = kept.empty((3, 4))                      # a is free now: handed out again
    assert d.ctypes.data == address
    assert len(kept.arrays) == 2


def test_shape_dtype_and_room():
    kept = KeptArrays(1)
    a = kept.empty(10, np.int32)
    address = a.ctypes.data
    del a
    assert kept.empty(10, np.float64).dtype == np.float64     # other dtype: a new one, kept
    b = kept.empty(6, np.float64, at_least=True)               # room enough: the kept one
    assert b.size == 10 and b.dtype == np.float64
    del b
    c = kept.empty((2, 5))                                     # other shape: new
    assert c.shape == (2, 5) and c.ctypes.data != address
