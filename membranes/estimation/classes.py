"""The classes of congruent patch blocks of one process and their inverses (§5, §6, §12).

`patches.PatchSystems` solves every patch with the inverse of its class's block: patches whose
translation invariant keys are equal (`congruence.patch_keys`) form one class. A `ClassStore`
keeps, for one kind of patch problem (the right-hand sides and solutions wanted), the keys seen
so far with their classes, each class's size, its block until it is inverted, and the part of
its inverse that the solves use.

**Across the levels of a hierarchy (§6).** The keys measure positions in units of the patch's
shortest edge, so a patch and its copy scaled by 2 on the next level of a uniform refinement
get equal keys; and their blocks in the canonical basis are equal too. The contravariant Piola
map of x ↦ s x sends a reference function φ̂ to φ(x) = s⁻¹ φ̂(x/s), so the mass entries
∫ φ_i·φ_j dx = ∫ φ̂_i·φ̂_j dx̂ and the divergence entries ∫ q ∇·φ dx = ∫ q̂ ∇̂·φ̂ dx̂ do not depend
on s. The multilevel flux's coarse patches on T_1 … T_J therefore share one store: a patch on
level j whose key an earlier level has seen uses that class's inverse, and only new classes
are assembled and inverted (BENCHMARKS.md counts them on the disk and the square). As within
one mesh, the divergence rows of a patch solved with its class's inverse are its own, and
every flux made is checked (`divergence`).
"""

import numpy as np

from .congruence import Blocks


class ClassStore:
    """Keys, classes and inverse parts for patch problems with right-hand sides `rhs` and
    solutions `solution` (see `PatchSystems`): `assign` classes to patches by their keys, `add`
    the new classes' blocks, `invert` classes."""

    def __init__(self, rhs="full", solution="full"):
        self.rhs, self.solution = rhs, solution
        self.blocks = Blocks()                       # blocks of the classes not yet inverted
        self.keys = np.zeros(0, dtype=np.uint64)     # sorted, with their classes
        self.key_class = np.zeros(0, dtype=np.int64)
        self.sizes = np.zeros((0, 2), dtype=np.int64)   # per class: its dofs and RT dofs
        self.row = np.zeros(0, dtype=np.int64)       # per class its row in `operators` (-1)
        self.operators = {}     # (n, n_σ) → (inputs, outputs, inverse parts (classes, out, in))

    def count(self):
        """The number of classes whose blocks were added."""
        return self.blocks.count()

    def shape(self, k):
        """(n, L, n_σ) of class k."""
        return self.blocks.shape(k)

    def assign(self, key, size, share=True):
        """Classes for patches with keys `key` and sizes `size` ((patches, 2): dofs, RT dofs):
        a new class for the first patch of each new key, and for any patch whose size differs
        from its key's class (a key collision: a class of its own); without `share`, one per
        patch. New classes are numbered on after all classes assigned so far; their blocks
        must then be added (`add`) in the order of `new`. Returns (classes of the patches,
        new: the patches whose blocks the new classes need, the number of collisions)."""
        count = self.sizes.shape[0]
        other = np.zeros(0, dtype=np.int64)
        if share:
            cls = self.lookup(key)
            new = np.flatnonzero(cls < 0)
            new = new[np.unique(key[new], return_index=True)[1]]         # one per new key
            self.remember(key[new], count + np.arange(new.size))
            sizes = np.concatenate([self.sizes, size[new]])
            cls = self.lookup(key)
            other = np.flatnonzero(np.any(sizes[cls] != size, axis=1))
            cls[other] = count + new.size + np.arange(other.size)
            new = np.concatenate([new, other])
        else:
            new = np.arange(key.size)
            cls = count + new
        self.sizes = np.concatenate([self.sizes, size[new]])
        return cls, new, other.size

    def lookup(self, key):
        """The classes of the keys (-1: not seen yet)."""
        keys = self.keys
        if not keys.size:
            return np.full(key.size, -1, dtype=np.int64)
        at = np.minimum(np.searchsorted(keys, key), keys.size - 1)
        return np.where(keys[at] == key, self.key_class[at], -1)

    def remember(self, key, cls):
        """Keys `key` stand for the classes `cls` from now on."""
        keys = np.concatenate([self.keys, key])
        order = np.argsort(keys, kind="stable")
        self.keys = keys[order]
        self.key_class = np.concatenate([self.key_class, cls])[order]

    def add(self, *block):
        """New classes for the blocks (`Blocks.add`); returns their numbers."""
        return self.blocks.add(*block)

    def invert(self, used):
        """The row of every class in `operators`, after making the inverse parts of the
        classes `used` that have none, per shape (n, n_σ) (raises np.linalg.LinAlgError for a
        singular block). The blocks are then dropped: only the inverses are kept."""
        count = self.count()
        row = np.concatenate([self.row, np.full(count - self.row.size, -1, dtype=np.int64)])
        todo = np.asarray(used, dtype=np.int64)
        todo = todo[row[todo] < 0]
        shape = np.array([self.shape(k) for k in todo.tolist()], dtype=np.int64).reshape(-1, 3)
        for size, rt in np.unique(shape[:, [0, 2]], axis=0).tolist():
            these = todo[(shape[:, 0] == size) & (shape[:, 2] == rt)]
            inputs = slice(rt if self.rhs == "divergence" else 0, size)
            outputs = slice(0, rt if self.solution == "flux" else size)
            made = self.blocks.operators(these, inputs, outputs)
            if (size, rt) in self.operators:
                made = np.concatenate([self.operators[size, rt][2], made])
            row[these] = np.arange(made.shape[0] - these.size, made.shape[0])
            self.operators[size, rt] = (inputs, outputs, made)
        self.row = row
        self.blocks.drop()
        return row
