"""User data formulas: a small, safe language for f1, f2 in x and y.

A formula such as ``-1 + 0.5*sin(pi*x)*max(y, 0)`` is parsed once with Python's :mod:`ast`
(never ``eval``) and can then be built twice from the same tree: as a UFL expression of the
spatial coordinate (for assembly) and as a numpy function (to check that the data are finite
on the mesh). Allowed: numbers, ``x``, ``y``, ``pi``, ``+ - * / **``, and the functions
``sin cos exp tanh sqrt abs min max``. Anything else is a :class:`ValueError` naming the problem,
and so is a formula nested deeper than MAX_DEPTH (Python's parser and the recursive builds
would fail with RecursionError or MemoryError), one of more than MAX_PARTS parts (below), or a
part without x, y that is not finite (``2**10**10``, ``1e400``), or a number that is not
(``tanh(1e400)``: a typo, not 1). Parts without x, y are evaluated once in double precision
(numpy's arithmetic, as on the mesh), so that the UFL build and the numpy check agree:
Python's float arithmetic raises where numpy's gives inf (``1/exp(1000)`` is 0 to both).

Size. The formula is written into the C code of every form that integrates the data (the loads,
the patch loads and the oscillation, §2, §5, §7), and a new formula compiles them on first use.
The C compiler's time and memory grow with the size of one kernel, in proportion up to some
MAX_PARTS parts (numbers, names, operations and calls of the syntax tree; a series of n terms
sin(k*x)*cos(k*y)/k**2 has 23 n - 2) and faster beyond (docs/performance.md has the figures).
Larger formulas are refused up front rather than left to the compiler. Nesting does not get
around it (balanced parentheses keep a long sum shallow); the size does not depend on the mesh,
and the quadrature of the data does not grow with the formula (a fixed rule,
`membranes.fem.quadrature`).
"""

import ast
import math
import numbers

import numpy as np
import ufl

# name -> (UFL builder, numpy builder, number of arguments; None for "two or more")
_FUNCTIONS = {
    "sin": (ufl.sin, np.sin, 1),
    "cos": (ufl.cos, np.cos, 1),
    "exp": (ufl.exp, np.exp, 1),
    "tanh": (ufl.tanh, np.tanh, 1),
    "sqrt": (ufl.sqrt, np.sqrt, 1),
    "abs": (abs, np.abs, 1),
    "min": (ufl.min_value, np.minimum, None),
    "max": (ufl.max_value, np.maximum, None),
}
_CONSTANTS = {"pi": math.pi}
_VARIABLES = ("x", "y")
_BINARY = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b,
           ast.Mult: lambda a, b: a * b, ast.Div: lambda a, b: a / b,
           ast.Pow: lambda a, b: a ** b}
_UNARY = {ast.USub: lambda a: -a, ast.UAdd: lambda a: a}
MAX_DEPTH = 500        # nesting of a formula (a sum of n terms nests n deep)
MAX_PARTS = 20000      # nodes of a formula's syntax tree (module notes: the C compiler's cost)
_SHOWN = 80            # characters of a formula quoted in a message


def _number(value):
    """A literal as a numpy double: an integer beyond its range is inf, as 1e400 is."""
    try:
        return np.float64(value)
    except OverflowError:
        return np.float64(np.inf if value > 0 else -np.inf)


def _depth(tree):
    """Nesting depth of an ast (iteratively: the tree may be too deep to recurse into)."""
    deepest, stack = 0, [(tree, 1)]
    while stack:
        node, d = stack.pop()
        deepest = max(deepest, d)
        stack.extend((child, d + 1) for child in ast.iter_child_nodes(node))
    return deepest


def _varies(node):
    """Whether the subtree `node` contains x or y."""
    return any(isinstance(n, ast.Name) and n.id in _VARIABLES for n in ast.walk(node))


class Formula:
    """A parsed data formula in x and y."""

    def __init__(self, text, name="expression"):
        if isinstance(text, Formula):
            text = text.text
        if isinstance(text, (bool, np.bool_)) or not isinstance(text, (str, numbers.Real)):
            raise ValueError(f"{name} must be a formula in x, y (text) or a number, got "
                             f"{text!r}")
        if isinstance(text, numbers.Real) and not math.isfinite(text):
            raise ValueError(f"{name} must be finite, got {text}")
        self.text = str(text)
        self.name = name
        shown = self.shown
        try:
            # (the minus sign of typeset text, U+2212, as a formula pasted from a paper has it)
            tree = ast.parse(self.text.strip().replace("\u2212", "-"), mode="eval")
        except SyntaxError as e:
            raise ValueError(f"{name}: cannot parse {shown!r} ({e.msg})") from None
        except (RecursionError, MemoryError):
            tree = None
        if tree is None or _depth(tree) > MAX_DEPTH:
            raise ValueError(f"{name}: the formula {shown!r} ({len(self.text)} characters) "
                             f"is nested too deeply (at most {MAX_DEPTH} levels; a sum of n "
                             f"terms nests n deep)")
        parts = sum(1 for _ in ast.walk(tree.body))
        if parts > MAX_PARTS:
            raise ValueError(f"{name}: the formula {shown!r} has {parts} parts (numbers, names, "
                             f"operations), more than {MAX_PARTS}: too large to compile (the "
                             f"C compiler's time grows faster than the formula)")
        self._tree = tree.body
        self._check(self._tree)
        self._check_constants(self._tree)

    @property
    def shown(self):
        """The formula as messages quote it: its first characters if it is long."""
        t = self.text
        return t if len(t) <= _SHOWN else f"{t[:_SHOWN - 3]}..."

    def _check_constants(self, node):
        """Refuse a largest part without x, y whose value (numpy's double arithmetic, as in
        `ufl`) is not finite: it would be inf or nan wherever the formula is evaluated."""
        if not _varies(node):
            if not np.isfinite(self._constant(node)):
                part = ast.get_source_segment(self.text.strip(), node) or ast.unparse(node)
                raise ValueError(f"{self.name}: {part[:_SHOWN]!r} is not finite in double "
                                 f"precision, in {self.shown!r}")
            return
        children = node.args if isinstance(node, ast.Call) else \
            [node.operand] if isinstance(node, ast.UnaryOp) else \
            [node.left, node.right] if isinstance(node, ast.BinOp) else []
        for child in children:
            self._check_constants(child)

    def _constant(self, node):
        with np.errstate(all="ignore"):
            return self._build(node, None, None, 1)

    def _check(self, node):
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
                raise ValueError(f"{self.name}: {node.value!r} is not a number in "
                                 f"{self.shown!r}")
            if not np.isfinite(_number(node.value)):   # (inside a finite part: tanh(1e400))
                part = ast.get_source_segment(self.text.strip(), node) or ast.unparse(node)
                raise ValueError(f"{self.name}: the number {part[:_SHOWN]!r} is not finite in "
                                 f"double precision, in {self.shown!r}")
        elif isinstance(node, ast.Name):
            if node.id not in _VARIABLES and node.id not in _CONSTANTS:
                raise ValueError(f"{self.name}: unknown name {node.id!r} in {self.shown!r} "
                                 f"(allowed: x, y, pi, {', '.join(_FUNCTIONS)})")
        elif isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            self._check(node.left)
            self._check(node.right)
        elif isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
            self._check(node.operand)
        elif isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in _FUNCTIONS:
                fname = node.func.id if isinstance(node.func, ast.Name) else ast.unparse(node.func)
                raise ValueError(f"{self.name}: unknown function {fname!r} in "
                                 f"{self.shown!r} "
                                 f"(allowed: {', '.join(_FUNCTIONS)})")
            nargs = _FUNCTIONS[node.func.id][2]
            if node.keywords or (nargs is not None and len(node.args) != nargs) \
                    or (nargs is None and len(node.args) < 2):
                want = nargs if nargs is not None else "at least 2"
                raise ValueError(f"{self.name}: {node.func.id}() takes {want} argument(s) "
                                 f"in {self.shown!r}")
            for a in node.args:
                self._check(a)
        else:
            raise ValueError(f"{self.name}: unsupported syntax {ast.unparse(node)[:_SHOWN]!r} "
                             f"in {self.shown!r}")

    def _build(self, node, x, y, which):
        if which == 0 and not _varies(node):   # a part without x, y: numpy's value (above)
            return float(self._constant(node))
        if isinstance(node, ast.Constant):   # numpy floats: 1/0 gives inf, not an exception
            return _number(node.value)
        if isinstance(node, ast.Name):
            value = {"x": x, "y": y}.get(node.id, _CONSTANTS.get(node.id))
            return value if which == 0 or node.id in _VARIABLES else np.float64(value)
        if isinstance(node, ast.BinOp):
            return _BINARY[type(node.op)](self._build(node.left, x, y, which),
                                          self._build(node.right, x, y, which))
        if isinstance(node, ast.UnaryOp):
            return _UNARY[type(node.op)](self._build(node.operand, x, y, which))
        fn = _FUNCTIONS[node.func.id][which]
        args = [self._build(a, x, y, which) for a in node.args]
        out = fn(args[0], args[1]) if len(args) > 1 else fn(args[0])
        for a in args[2:]:
            out = fn(out, a)
        return out

    def ufl(self, x):
        """The formula as a UFL expression of the spatial coordinate ``x`` (shape (2,))."""
        return self._build(self._tree, x[0], x[1], 0)

    def numpy(self, points):
        """The formula at ``points`` of shape (2, n) or (3, n); returns an array of length n."""
        points = np.asarray(points, dtype=float)
        with np.errstate(all="ignore"):
            v = self._build(self._tree, points[0], points[1], 1)
        return np.broadcast_to(np.asarray(v, dtype=float), points[0].shape)

    def __repr__(self):
        return f"Formula({self.text!r})"
