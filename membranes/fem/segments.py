"""Segments of index arrays: the entries of segments given by their starts and lengths, as
one array (the patch engine's routes, §12, and the mesh conformity checks' pieces)."""

import numpy as np


def ranges(starts, lengths):
    """The concatenation of arange(s, s + n) over zip(starts, lengths) (int64): the entries of
    segments given by their starts and lengths, as one cumulative sum of steps (1 within a
    segment, the jump to the next segment's start at its first entry)."""
    starts = np.asarray(starts, dtype=np.int64)
    lengths = np.asarray(lengths, dtype=np.int64)
    if np.any(lengths == 0):
        starts, lengths = starts[lengths > 0], lengths[lengths > 0]
    ends = np.cumsum(lengths)
    out = np.ones(int(ends[-1]) if ends.size else 0, dtype=np.int64)
    if out.size:
        out[0] = starts[0]
        out[ends[:-1]] = starts[1:] - starts[:-1] - lengths[:-1] + 1
        np.cumsum(out, out=out)
    return out
