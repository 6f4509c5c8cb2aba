"""Read FLAME pickles without chumpy, and without running anything a file names.

The official FLAME pickles (``generic_model.pkl``, ``flame2023.pkl``) and ``FLAME_masks.pkl`` were
written by Python 2 with chumpy objects and a scipy sparse matrix inside. Python's own unpickler
imports and calls whatever global a file names, so a crafted file runs code however the
unpickler's ``find_class`` is restricted (dotted names, builtins reachable through modules,
``BUILD`` on classes). This module therefore does not use it: :class:`_Machine` is a small pickle
interpreter of its own. ``pickletools.genops`` decodes the opcodes (pure decoding, nothing is
resolved or called), and the machine executes only the opcodes a FLAME file needs:

- literals (ints, floats, strings, bytes, ``None``, bools), tuples, lists, dicts, sets, the memo,
  ``MARK``/``POP``/``DUP``, protocol and framing opcodes;
- ``GLOBAL``/``STACK_GLOBAL`` resolve an exact ``(module, name)`` pair from :data:`ALLOWED` to one
  of this module's own :class:`_Global` handlers. Nothing is imported and no attribute of any
  module is looked up; a dotted name, any other pair, and any chumpy class other than the four
  stand-ins are refused;
- ``REDUCE``, ``NEWOBJ`` and ``BUILD`` act only on those handlers and the builders they return
  (arrays, dtypes, chumpy and sparse stand-ins);
- every other opcode (``INST``, ``OBJ``, ``NEWOBJ_EX``, extension registry codes, persistent ids,
  out-of-band buffers) is refused.

What the handlers rebuild: numpy arrays (``_reconstruct`` + state, protocol-5 ``_frombuffer``),
dtypes of plain numeric, bool and string kinds (no object, structured or sub-array dtypes), numpy
scalars, ``_codecs.encode`` for latin-1 bytes, ``OrderedDict`` (as a dict), sets; chumpy ``Ch``
(evaluates to its ``x``), ``Select`` (``a.ravel()[idxs].reshape(preferred_shape)``), ``Reshape``
and ``Transpose``; scipy ``csc_matrix``/``csr_matrix`` under their old and new module names
(densified). A chumpy expression that needs chumpy's graph machinery (a lazy sum, say) raises
:class:`UnsupportedPickle` naming the class.

The guarantee, by construction: the only callables a file can reach are the handlers below, and
each of them checks its arguments' types; reading a file can build arrays and plain containers,
nothing else. ``tests/test_unpickle_security.py`` runs a corpus of known bypass payloads through
every route a FLAME file takes and checks that none of them runs (docs/workspace.md "Files that
cannot run code").
"""

from __future__ import annotations

import io
import pickletools
import re
import reprlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError


class UnsupportedPickle(ValueError):
    """A pickle cannot be read into plain arrays (malformed, or a construct this reader lacks)."""


class RefusedPickle(UnsupportedPickle):
    """A pickle names a global or uses an opcode outside the allow-list; nothing of it ran."""


MAX_DEPTH = 64
"""Deepest nesting of containers and chumpy expressions accepted in a FLAME pickle."""

MAX_NODES = 1 << 20
"""Most values a FLAME pickle may expand to, each reference to a shared (memo) object counted again.

A real FLAME pickle holds a few dozen keys, each an array or a chumpy/sparse object of a handful of
entries (an array counts as one value however large: its size is bounded by the file's bytes), so
it has well under a thousand. 1,048,576 still admits a model whose vertices, faces, weights and
pose blend shapes are nested Python lists instead of arrays, and refuses a file whose memo
references double at every level (the "billion laughs": 20 levels of ``[L, L]`` are 2 million
values) before the expansion costs memory or time. Conversion is memoised by object identity, so
its work is linear in the file's distinct objects."""

MAX_DENSE_ELEMENTS = 1 << 27
"""Most elements a sparse matrix may densify to (1 GiB of float64). FLAME's ``J_regressor`` is
5 x 5023 (about 5 x 5143 with teeth); a file declaring a larger matrix is refused rather than
allocated."""


def _brief(value: Any) -> str:
    """A short repr of a value a file built (bounded in depth and length, whatever its nesting)."""
    return reprlib.repr(value)


# --------------------------------------------------------------------------------------------
# Builders: objects a file can construct, and how BUILD fills them
# --------------------------------------------------------------------------------------------


class _Builder:
    """Something a handler made that a ``BUILD`` opcode may complete."""

    def build(self, state: Any) -> None:
        raise RefusedPickle(f"BUILD is not allowed on {type(self).__name__}")


@dataclass(eq=False)
class _DtypeBuilder(_Builder):
    dtype: np.dtype

    def build(self, state: Any) -> None:
        # numpy's dtype state: (version, byteorder, subarray, names, fields, elsize, alignment, flags[, metadata])
        if not isinstance(state, tuple) or len(state) < 5:
            raise UnsupportedPickle("malformed dtype state")
        order, subarray, names, fields = state[1], state[2], state[3], state[4]
        if subarray is not None or names is not None or fields is not None:
            raise RefusedPickle("structured and sub-array dtypes are not accepted")
        if order in ("<", ">") and self.dtype.itemsize > 1:
            self.dtype = self.dtype.newbyteorder(order)
        if self.dtype.kind in "SU" and len(state) > 5 and isinstance(state[5], int) and state[5] > 0:
            size = state[5] // (4 if self.dtype.kind == "U" else 1)
            self.dtype = np.dtype(f"{self.dtype.byteorder if self.dtype.byteorder in '<>' else ''}{self.dtype.kind}{size}")


@dataclass(eq=False)
class _ArrayBuilder(_Builder):
    array: np.ndarray | None = None

    def build(self, state: Any) -> None:
        # ndarray state: (version, shape, dtype, is_fortran, raw) or, without the version, the last four
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise UnsupportedPickle("malformed array state")
        shape, dtype, fortran, raw = state[-4:]
        self.array = _array_from_bytes(raw, _dtype(dtype), shape, "F" if fortran else "C")


@dataclass(eq=False)
class ChumpyStub(_Builder):
    """A chumpy object: its module, class name and state dict (evaluated by :func:`to_plain`)."""

    module: str
    name: str
    state: dict[str, Any] = field(default_factory=dict)

    def build(self, state: Any) -> None:
        self.state.update(_state_dict(state, f"chumpy object {self.module}.{self.name}"))


@dataclass(eq=False)
class SparseStub(_Builder):
    """A scipy sparse matrix (``csc`` or ``csr``) as its state dict (densified by :func:`to_plain`)."""

    fmt: str
    state: dict[str, Any] = field(default_factory=dict)

    def build(self, state: Any) -> None:
        self.state.update(_state_dict(state, f"sparse {self.fmt} matrix"))


def _state_dict(state: Any, what: str) -> dict[str, Any]:
    """An object's pickled state as one dict (``(dict, slots)`` pairs merged); strings as keys."""
    parts = state if isinstance(state, tuple) and len(state) == 2 else (state,)
    out: dict[str, Any] = {}
    for part in parts:
        if part is None:
            continue
        if not isinstance(part, dict) or not all(isinstance(k, str) for k in part):
            raise UnsupportedPickle(f"{what}: state is not a dict with string keys")
        out.update(part)
    return out


# --------------------------------------------------------------------------------------------
# Globals: the exact (module, name) pairs a file may name, each mapped to a handler
# --------------------------------------------------------------------------------------------

_DTYPE_CODE = re.compile(r"^[<>=|]?(?:[?bBhHiIlLqQefdgFDG]|[biufc][1-9][0-9]?|[SU][0-9]{0,9})$")


def _dtype(x: Any) -> np.dtype:
    if isinstance(x, _DtypeBuilder):
        return x.dtype
    raise UnsupportedPickle(f"expected a dtype, found {type(x).__name__}")


def _new_dtype(code: Any, *_flags: Any) -> _DtypeBuilder:
    if isinstance(code, bytes):
        code = code.decode("latin1")
    if not isinstance(code, str) or not _DTYPE_CODE.match(code):
        raise RefusedPickle(f"dtype {_brief(code)} is not accepted (numeric, bool and string dtypes only)")
    dt = np.dtype(code)
    if dt.kind not in "biufcSU" or dt.hasobject:
        raise RefusedPickle(f"dtype {_brief(code)} is not accepted")
    return _DtypeBuilder(dt)


def _as_bytes(raw: Any) -> bytes:
    if isinstance(raw, (bytes, bytearray)):
        return bytes(raw)
    if isinstance(raw, str):  # Python 2 str read with encoding="latin1"
        return raw.encode("latin1")
    raise RefusedPickle(f"array data must be bytes, found {type(raw).__name__} (object arrays are not accepted)")


def _shape(shape: Any) -> tuple[int, ...]:
    if isinstance(shape, int) and not isinstance(shape, bool):
        shape = (shape,)
    if not isinstance(shape, (tuple, list)) or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
        raise UnsupportedPickle(f"malformed array shape {_brief(shape)}")
    return tuple(shape)


def _array_from_bytes(raw: Any, dtype: np.dtype, shape: Any, order: str) -> np.ndarray:
    data = _as_bytes(raw)
    shp = _shape(shape)
    count = int(np.prod(shp, dtype=np.int64)) if shp else 1
    if count * dtype.itemsize != len(data):
        raise UnsupportedPickle(f"array data holds {len(data)} bytes, shape {shp} of {dtype} needs {count * dtype.itemsize}")
    flat = np.frombuffer(data, dtype=dtype, count=count)
    return flat.reshape(shp, order=order).copy(order="C")


class _Global:
    """What a permitted global stands for: how ``REDUCE`` calls it and ``NEWOBJ`` instantiates it."""

    def __init__(self, label: str, reduce: Callable[..., Any] | None = None,
                 newobj: Callable[..., Any] | None = None) -> None:
        self.label = label
        self._reduce = reduce
        self._newobj = newobj

    def reduce(self, args: tuple) -> Any:
        if self._reduce is None:
            raise RefusedPickle(f"{self.label} cannot be called")
        try:
            return self._reduce(*args)
        except TypeError as exc:
            raise UnsupportedPickle(f"{self.label}: bad arguments ({exc})") from None

    def newobj(self, args: tuple) -> Any:
        if self._newobj is None:
            raise RefusedPickle(f"{self.label} cannot be instantiated")
        return self._newobj(*args)

    def __repr__(self) -> str:
        return f"<{self.label}>"


_NDARRAY = _Global("numpy.ndarray")
_OBJECT = _Global("object")


def _reconstruct(cls: Any, shape: Any, dtype_code: Any) -> _ArrayBuilder:
    if cls is not _NDARRAY:
        raise RefusedPickle("numpy _reconstruct is only accepted for numpy.ndarray")
    return _ArrayBuilder()


def _frombuffer(buf: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
    if order not in ("C", "F"):
        raise UnsupportedPickle(f"bad array order {_brief(order)}")
    return _array_from_bytes(buf, _dtype(dtype), shape, order)


def _scalar(dtype: Any, raw: Any = None) -> Any:
    dt = _dtype(dtype)
    return _array_from_bytes(raw, dt, (), "C")[()]


def _codecs_encode(text: Any, encoding: Any = "utf-8") -> bytes:
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise RefusedPickle("_codecs.encode is only accepted for latin-1 text")
    return text.encode("latin1")


def _empty_bytes() -> bytes:
    # protocols 0-2 write an empty bytes object as bytes() (non-empty ones go through _codecs.encode)
    return b""


def _ordered_dict(items: Any = ()) -> dict:
    out: dict = {}
    for pair in items:
        if not isinstance(pair, (tuple, list)) or len(pair) != 2:
            raise UnsupportedPickle("OrderedDict items are not pairs")
        out[_key(pair[0])] = pair[1]
    return out


def _set(items: Any = ()) -> set:
    if not isinstance(items, (list, tuple, set, frozenset)):
        raise UnsupportedPickle("set items are not a list")
    return {_key(v) for v in items}


def _frozenset(items: Any = ()) -> frozenset:
    return frozenset(_set(items))


def _stub_global(label: str, make: Callable[[], _Builder]) -> _Global:
    return _Global(label, reduce=lambda *args: make(), newobj=lambda *args: make())


def _reconstructor(cls: Any, base: Any, state: Any = None) -> _Builder:
    # copyreg._reconstructor(cls, object, None): the protocol 0/1 form of "a new instance of cls"
    if not isinstance(cls, _Global) or base is not _OBJECT or state is not None:
        raise RefusedPickle("copyreg._reconstructor is only accepted for the chumpy and sparse stand-ins")
    return cls.newobj(())


_CHUMPY_NAMES = (("chumpy.ch", "Ch"), ("chumpy", "Ch"), ("chumpy.reordering", "Select"),
                 ("chumpy.reordering", "Reshape"), ("chumpy.reordering", "Transpose"))
_SPARSE_NAMES = (("scipy.sparse.csc", "csc_matrix"), ("scipy.sparse._csc", "csc_matrix"),
                 ("scipy.sparse.csr", "csr_matrix"), ("scipy.sparse._csr", "csr_matrix"))


def _build_allowed() -> dict[tuple[str, str], _Global]:
    table: dict[tuple[str, str], _Global] = {}
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        table[(mod, "_reconstruct")] = _Global(f"{mod}._reconstruct", reduce=_reconstruct)
        table[(mod, "scalar")] = _Global(f"{mod}.scalar", reduce=_scalar)
    for mod in ("numpy.core.numeric", "numpy._core.numeric"):
        table[(mod, "_frombuffer")] = _Global(f"{mod}._frombuffer", reduce=_frombuffer)
    table[("numpy", "ndarray")] = _NDARRAY
    table[("numpy", "dtype")] = _Global("numpy.dtype", reduce=_new_dtype)
    table[("_codecs", "encode")] = _Global("_codecs.encode", reduce=_codecs_encode)
    table[("collections", "OrderedDict")] = _Global("collections.OrderedDict", reduce=_ordered_dict)
    for mod in ("copyreg", "copy_reg"):
        table[(mod, "_reconstructor")] = _Global(f"{mod}._reconstructor", reduce=_reconstructor)
    for mod in ("builtins", "__builtin__"):
        table[(mod, "object")] = _OBJECT
        table[(mod, "set")] = _Global(f"{mod}.set", reduce=_set)
        table[(mod, "frozenset")] = _Global(f"{mod}.frozenset", reduce=_frozenset)
        table[(mod, "bytes")] = _Global(f"{mod}.bytes", reduce=_empty_bytes)
    for mod, name in _CHUMPY_NAMES:
        table[(mod, name)] = _stub_global(f"{mod}.{name}", lambda m=mod, n=name: ChumpyStub(m, n))
    for mod, name in _SPARSE_NAMES:
        table[(mod, name)] = _stub_global(f"{mod}.{name}", lambda f=name[:3]: SparseStub(f))
    return table


ALLOWED: dict[tuple[str, str], _Global] = _build_allowed()
"""The exact ``(module, name)`` pairs a FLAME pickle may name, and what each stands for."""

_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def resolve_global(module: str, name: str) -> _Global:
    """The handler of an exact ``(module, name)`` pair; :class:`RefusedPickle` for anything else."""
    handler = ALLOWED.get((module, name))
    if handler is not None:
        return handler
    if (module == "chumpy" or module.startswith("chumpy.")) and _IDENT.match(name):
        raise UnsupportedPickle(f"cannot evaluate chumpy object {module}.{name} without chumpy")
    raise RefusedPickle(f"refusing to load global {module}.{name} (not on the allow-list)")


# --------------------------------------------------------------------------------------------
# The machine
# --------------------------------------------------------------------------------------------


class _Mark:
    pass


_MARK = _Mark()


def _key(k: Any) -> Any:
    if isinstance(k, (str, bytes, int, float, bool, type(None))):
        return k
    if isinstance(k, tuple) and all(isinstance(v, (str, bytes, int, float, bool, type(None))) for v in k):
        return k
    raise UnsupportedPickle(f"unsupported dict key of type {type(k).__name__}")


class _Machine:
    """Executes the decoded opcodes of one pickle (see the module doc for what is accepted)."""

    def __init__(self) -> None:
        self.stack: list[Any] = []
        self.memo: dict[int, Any] = {}
        self.done = False
        self.result: Any = None

    # stack helpers
    def pop(self) -> Any:
        if not self.stack:
            raise UnsupportedPickle("stack underflow")
        v = self.stack.pop()
        if v is _MARK:
            raise UnsupportedPickle("unexpected mark")
        return v

    def top(self) -> Any:
        if not self.stack or self.stack[-1] is _MARK:
            raise UnsupportedPickle("stack underflow")
        return self.stack[-1]

    def pop_mark(self) -> list[Any]:
        for i in range(len(self.stack) - 1, -1, -1):
            if self.stack[i] is _MARK:
                items = self.stack[i + 1:]
                del self.stack[i:]
                return items
        raise UnsupportedPickle("mark not found")

    def run(self, stream: io.BufferedIOBase | io.BytesIO) -> Any:
        try:
            for op, arg, _pos in pickletools.genops(stream):
                if self.done:
                    break
                handler = _OPS.get(op.name)
                if handler is None:
                    raise RefusedPickle(f"opcode {op.name} is not accepted")
                handler(self, arg)
        except RecursionError:
            raise UnsupportedPickle(f"nested too deeply to read (limit {MAX_DEPTH} levels)") from None
        except (ValueError, EOFError, OverflowError, MemoryError) as exc:
            if isinstance(exc, UnsupportedPickle):
                raise
            raise UnsupportedPickle(f"not a readable pickle ({exc})") from None
        if not self.done:
            raise UnsupportedPickle("pickle ends before its STOP opcode")
        return self.result


def _push(value_of: Callable[[Any], Any]) -> Callable[[_Machine, Any], None]:
    def op(m: _Machine, arg: Any) -> None:
        m.stack.append(value_of(arg))
    return op


def _op_stop(m: _Machine, _arg: Any) -> None:
    m.result = m.pop()
    m.done = True


def _op_string(m: _Machine, arg: Any) -> None:
    m.stack.append(arg.decode("latin1") if isinstance(arg, bytes) else arg)


def _op_value(m: _Machine, arg: Any) -> None:
    m.stack.append(arg)


def _op_mark(m: _Machine, _arg: Any) -> None:
    m.stack.append(_MARK)


def _op_pop(m: _Machine, _arg: Any) -> None:
    if not m.stack:
        raise UnsupportedPickle("stack underflow")
    m.stack.pop()


def _op_pop_mark(m: _Machine, _arg: Any) -> None:
    m.pop_mark()


def _op_dup(m: _Machine, _arg: Any) -> None:
    m.stack.append(m.top())


def _op_put(m: _Machine, arg: Any) -> None:
    m.memo[int(arg)] = m.top()


def _op_memoize(m: _Machine, _arg: Any) -> None:
    m.memo[len(m.memo)] = m.top()


def _op_get(m: _Machine, arg: Any) -> None:
    if arg not in m.memo:
        raise UnsupportedPickle(f"memo key {arg} not found")
    m.stack.append(m.memo[arg])


def _op_tuple(m: _Machine, _arg: Any) -> None:
    m.stack.append(tuple(m.pop_mark()))


def _tuple_n(n: int) -> Callable[[_Machine, Any], None]:
    def op(m: _Machine, _arg: Any) -> None:
        items = [m.pop() for _ in range(n)][::-1]
        m.stack.append(tuple(items))
    return op


def _op_list(m: _Machine, _arg: Any) -> None:
    m.stack.append(m.pop_mark())


def _op_append(m: _Machine, _arg: Any) -> None:
    v = m.pop()
    target = m.top()
    if not isinstance(target, list):
        raise RefusedPickle(f"APPEND on {type(target).__name__}")
    target.append(v)


def _op_appends(m: _Machine, _arg: Any) -> None:
    items = m.pop_mark()
    target = m.top()
    if not isinstance(target, list):
        raise RefusedPickle(f"APPENDS on {type(target).__name__}")
    target.extend(items)


def _op_dict(m: _Machine, _arg: Any) -> None:
    items = m.pop_mark()
    if len(items) % 2:
        raise UnsupportedPickle("odd number of items for DICT")
    m.stack.append({_key(items[i]): items[i + 1] for i in range(0, len(items), 2)})


def _op_setitem(m: _Machine, _arg: Any) -> None:
    v = m.pop()
    k = m.pop()
    target = m.top()
    if not isinstance(target, dict):
        raise RefusedPickle(f"SETITEM on {type(target).__name__}")
    target[_key(k)] = v


def _op_setitems(m: _Machine, _arg: Any) -> None:
    items = m.pop_mark()
    target = m.top()
    if not isinstance(target, dict) or len(items) % 2:
        raise RefusedPickle("SETITEMS on something that is not a dict")
    for i in range(0, len(items), 2):
        target[_key(items[i])] = items[i + 1]


def _op_additems(m: _Machine, _arg: Any) -> None:
    items = m.pop_mark()
    target = m.top()
    if not isinstance(target, set):
        raise RefusedPickle(f"ADDITEMS on {type(target).__name__}")
    target.update(_key(v) for v in items)


def _op_frozenset(m: _Machine, _arg: Any) -> None:
    m.stack.append(frozenset(_key(v) for v in m.pop_mark()))


def _op_global(m: _Machine, arg: Any) -> None:
    if not isinstance(arg, str) or arg.count(" ") != 1:
        raise UnsupportedPickle("malformed GLOBAL")
    module, name = arg.split(" ")
    m.stack.append(resolve_global(module, name))


def _op_stack_global(m: _Machine, _arg: Any) -> None:
    name = m.pop()
    module = m.pop()
    if not isinstance(module, str) or not isinstance(name, str):
        raise UnsupportedPickle("STACK_GLOBAL needs two strings")
    m.stack.append(resolve_global(module, name))


def _op_reduce(m: _Machine, _arg: Any) -> None:
    args = m.pop()
    func = m.pop()
    if not isinstance(func, _Global) or not isinstance(args, tuple):
        raise RefusedPickle(f"REDUCE of {type(func).__name__} is not accepted")
    m.stack.append(func.reduce(args))


def _op_newobj(m: _Machine, _arg: Any) -> None:
    args = m.pop()
    cls = m.pop()
    if not isinstance(cls, _Global) or not isinstance(args, tuple):
        raise RefusedPickle(f"NEWOBJ of {type(cls).__name__} is not accepted")
    m.stack.append(cls.newobj(args))


def _op_build(m: _Machine, _arg: Any) -> None:
    state = m.pop()
    target = m.top()
    if not isinstance(target, _Builder):
        raise RefusedPickle(f"BUILD on {type(target).__name__} is not accepted")
    target.build(state)
    if isinstance(target, _ArrayBuilder):  # a finished array replaces its builder (memo entries follow in to_plain)
        m.stack[-1] = target.array


def _op_bytearray(m: _Machine, arg: Any) -> None:
    m.stack.append(bytes(arg))


_OPS: dict[str, Callable[[_Machine, Any], None]] = {
    "PROTO": lambda m, a: None, "FRAME": lambda m, a: None, "STOP": _op_stop,
    "MARK": _op_mark, "POP": _op_pop, "POP_MARK": _op_pop_mark, "DUP": _op_dup,
    "NONE": _push(lambda a: None), "NEWTRUE": _push(lambda a: True), "NEWFALSE": _push(lambda a: False),
    "INT": _op_value, "BININT": _op_value, "BININT1": _op_value, "BININT2": _op_value,
    "LONG": _op_value, "LONG1": _op_value, "LONG4": _op_value, "FLOAT": _op_value, "BINFLOAT": _op_value,
    "STRING": _op_string, "BINSTRING": _op_string, "SHORT_BINSTRING": _op_string,
    "UNICODE": _op_value, "BINUNICODE": _op_value, "SHORT_BINUNICODE": _op_value, "BINUNICODE8": _op_value,
    "BINBYTES": _op_value, "SHORT_BINBYTES": _op_value, "BINBYTES8": _op_value, "BYTEARRAY8": _op_bytearray,
    "EMPTY_TUPLE": _push(lambda a: ()), "TUPLE": _op_tuple, "TUPLE1": _tuple_n(1), "TUPLE2": _tuple_n(2),
    "TUPLE3": _tuple_n(3), "EMPTY_LIST": _push(lambda a: []), "LIST": _op_list, "APPEND": _op_append,
    "APPENDS": _op_appends, "EMPTY_DICT": _push(lambda a: {}), "DICT": _op_dict, "SETITEM": _op_setitem,
    "SETITEMS": _op_setitems, "EMPTY_SET": _push(lambda a: set()), "ADDITEMS": _op_additems,
    "FROZENSET": _op_frozenset,
    "PUT": _op_put, "BINPUT": _op_put, "LONG_BINPUT": _op_put, "MEMOIZE": _op_memoize,
    "GET": _op_get, "BINGET": _op_get, "LONG_BINGET": _op_get,
    "GLOBAL": _op_global, "STACK_GLOBAL": _op_stack_global,
    "REDUCE": _op_reduce, "NEWOBJ": _op_newobj, "BUILD": _op_build,
}
"""Opcode name -> implementation; any opcode not listed is refused."""


# --------------------------------------------------------------------------------------------
# Plain values
# --------------------------------------------------------------------------------------------


def _sparse_to_dense(obj: SparseStub, conv: _Converter, depth: int) -> np.ndarray:
    """A sparse stand-in as a dense array; refused past :data:`MAX_DENSE_ELEMENTS` elements."""
    import scipy.sparse

    st = obj.state
    shape = st.get("_shape", st.get("shape"))
    if shape is None:
        raise UnsupportedPickle("sparse matrix lacks its shape")
    shape = _shape(tuple(shape) if isinstance(shape, list) else shape)
    if len(shape) != 2:
        raise UnsupportedPickle(f"sparse matrix shape {_brief(shape)} is not 2-D")
    if shape[0] * shape[1] > MAX_DENSE_ELEMENTS:
        raise UnsupportedPickle(f"sparse matrix of shape {shape[0]}x{shape[1]} is too large to densify "
                                f"({shape[0] * shape[1]} elements, at most {MAX_DENSE_ELEMENTS})")
    try:
        data = np.asarray(conv.plain(st["data"], depth + 1))
        indices = np.asarray(conv.plain(st["indices"], depth + 1))
        indptr = np.asarray(conv.plain(st["indptr"], depth + 1))
    except KeyError as exc:
        raise UnsupportedPickle(f"sparse matrix lacks {exc.args[0]!r}") from None
    for name, arr in (("data", data), ("indices", indices), ("indptr", indptr)):
        if arr.dtype.kind not in ("iuf" if name == "data" else "iu"):
            raise UnsupportedPickle(f"sparse matrix {name} has dtype {arr.dtype}")
    cls = scipy.sparse.csc_matrix if obj.fmt == "csc" else scipy.sparse.csr_matrix
    try:
        return np.asarray(cls((data, indices, indptr), shape=shape).toarray())
    except (ValueError, IndexError, TypeError, OverflowError) as exc:
        raise UnsupportedPickle(f"malformed sparse matrix ({exc})") from None


def _ints(value: Any, what: str) -> tuple[int, ...]:
    """A converted shape or axes list as Python ints (UnsupportedPickle for anything else)."""
    try:
        return tuple(int(v) for v in value)
    except (TypeError, ValueError, OverflowError):
        raise UnsupportedPickle(f"malformed {what} {_brief(value)}") from None


def _chumpy_to_array(obj: ChumpyStub, conv: _Converter, depth: int) -> np.ndarray:
    """The value of one of the chumpy stand-ins (module doc); UnsupportedPickle for the others."""
    st = obj.state
    name = obj.name
    try:
        if name == "Select" and "a" in st and "idxs" in st:
            base = np.asarray(conv.plain(st["a"], depth + 1))
            out = base.ravel()[np.asarray(conv.plain(st["idxs"], depth + 1)).ravel()]
            shape = conv.plain(st.get("preferred_shape"), depth + 1)
            return out.reshape(_ints(shape, "Select shape")) if shape is not None else out
        if name == "Reshape" and "a" in st and "shape" in st:
            arr = np.asarray(conv.plain(st["a"], depth + 1))
            return arr.reshape(_ints(conv.plain(st["shape"], depth + 1), "Reshape shape"))
        if name == "Transpose" and "a" in st:
            axes = conv.plain(st.get("axes"), depth + 1)
            arr = np.asarray(conv.plain(st["a"], depth + 1))
            return arr.transpose(_ints(axes, "Transpose axes")) if axes is not None else arr.T
    except (ValueError, IndexError, TypeError, OverflowError) as exc:
        if isinstance(exc, UnsupportedPickle):
            raise
        raise UnsupportedPickle(f"malformed chumpy object {obj.module}.{name} ({exc})") from None
    if "x" in st:
        return np.asarray(conv.plain(st["x"], depth + 1))
    raise UnsupportedPickle(f"cannot evaluate chumpy object {obj.module}.{name} without chumpy")


_SHARED = (dict, list, tuple, set, frozenset, _Builder)
"""The kinds of object a file can reference more than once through the memo."""


class _Converter:
    """Turns the machine's result into plain values, each shared object once.

    An object the file references several times (memo ``GET``) is converted on its first visit and
    its result reused, so the work is linear in the file's distinct objects. :attr:`count` adds up
    the values the result expands to, a shared object counted again at every reference; past
    :data:`MAX_NODES` the file is refused, so nothing downstream (``np.asarray`` of a nested list)
    expands it either.
    """

    def __init__(self) -> None:
        self.count = 0
        self._memo: dict[int, tuple[Any, Any, int]] = {}  # id -> (object kept alive, plain value, its count)

    def _add(self, n: int) -> None:
        self.count += n
        if self.count > MAX_NODES:
            raise UnsupportedPickle(f"expands to more than {MAX_NODES} values (shared objects repeated at every "
                                    "reference); a FLAME file holds a few dozen arrays")

    def plain(self, value: Any, depth: int = 0) -> Any:
        """``value`` with its stand-ins turned into numpy arrays; dicts, lists and tuples walked.

        Raises :class:`UnsupportedPickle` past :data:`MAX_DEPTH` levels or :data:`MAX_NODES` values,
        for a builder a file never completed, and for any value that is not plain data.
        """
        if depth > MAX_DEPTH:
            raise UnsupportedPickle(f"nested deeper than {MAX_DEPTH} levels")
        if not isinstance(value, _SHARED):
            self._add(1)
            return self._leaf(value)
        seen = self._memo.get(id(value))
        if seen is not None:
            self._add(seen[2])
            return seen[1]
        start = self.count
        self._add(1)
        out = self._node(value, depth)
        self._memo[id(value)] = (value, out, self.count - start)
        return out

    def _node(self, value: Any, depth: int) -> Any:
        """One container or builder, its parts converted."""
        if isinstance(value, ChumpyStub):
            return _chumpy_to_array(value, self, depth)
        if isinstance(value, SparseStub):
            return _sparse_to_dense(value, self, depth)
        if isinstance(value, _ArrayBuilder):
            if value.array is None:
                raise UnsupportedPickle("an array without its data")
            return value.array
        if isinstance(value, _DtypeBuilder):
            return value.dtype
        if isinstance(value, dict):
            return {k: self.plain(v, depth + 1) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return type(value)(self.plain(v, depth + 1) for v in value)
        if isinstance(value, (set, frozenset)):
            self._add(len(value))
            return type(value)(value)
        raise UnsupportedPickle(f"a {type(value).__name__} is not a value")

    @staticmethod
    def _leaf(value: Any) -> Any:
        """A value that holds no others: returned as it is unless it is a bare global."""
        if isinstance(value, _Global):
            raise UnsupportedPickle(f"a bare reference to {value.label} is not a value")
        return value


def to_plain(value: Any, depth: int = 0) -> Any:
    """Recursively turn stand-ins into numpy arrays; dicts, lists and tuples are walked.

    Raises :class:`UnsupportedPickle` past :data:`MAX_DEPTH` levels or :data:`MAX_NODES` values
    (:class:`_Converter`), for a builder a file never completed, and for any value that is not plain
    data.
    """
    return _Converter().plain(value, depth)


def loads_flame_pickle(data: bytes) -> Any:
    """Run the restricted machine on pickle bytes; the raw result (stand-ins not yet evaluated)."""
    return _Machine().run(io.BytesIO(data))


def _plain_dict(raw: dict[Any, Any]) -> dict[str, Any]:
    """The machine's top-level dict as str -> numpy array (strings kept as strings)."""
    conv = _Converter()
    out: dict[str, Any] = {}
    for key, value in raw.items():
        value = conv.plain(value)
        if isinstance(value, (bytes, str)):
            out[str(key)] = value.decode("latin1") if isinstance(value, bytes) else value
        else:
            try:
                out[str(key)] = np.asarray(value)
            except (ValueError, TypeError):
                out[str(key)] = value
    return out


def load_flame_pickle(path: str | Path) -> dict[str, Any]:
    """Load a FLAME-style pickle into a dict of plain values, without running anything it names.

    Arrays (including chumpy and sparse values) come back as numpy arrays; strings stay strings.
    Raises :class:`UnsupportedPickle` (:class:`RefusedPickle` for a forbidden global or opcode),
    also for values that cannot be converted (too large, too deep, out of range), or ``OSError``.
    """
    with open(path, "rb") as fh:
        raw = _Machine().run(fh)
    if not isinstance(raw, dict):
        raise UnsupportedPickle(f"expected a dict at the top level, found {type(raw).__name__}")
    try:
        return _plain_dict(raw)
    except RecursionError:
        raise UnsupportedPickle(f"nested too deeply to convert (limit {MAX_DEPTH} levels)") from None
    except MemoryError:
        raise UnsupportedPickle("its arrays do not fit in memory") from None
    except (ValueError, TypeError, IndexError, OverflowError) as exc:
        if isinstance(exc, UnsupportedPickle):
            raise
        raise UnsupportedPickle(f"cannot convert its values to arrays ({type(exc).__name__}: {exc})") from None


def read_flame_pickle(path: Path, kind: str, what: str) -> dict[str, Any]:
    """:func:`load_flame_pickle`, with every failure as an InputError naming ``path``.

    kind: the file's kind in the message ("FLAME pickle", "mask pickle"); what: what could not be
    read ("the FLAME model", "the mask file").
    """
    try:
        return load_flame_pickle(path)
    except UnsupportedPickle as exc:
        raise InputError(path, f"not a readable {kind}: {exc}") from None
    except OSError as exc:
        raise InputError(path, f"cannot read {what} ({exc.strerror or exc})") from None