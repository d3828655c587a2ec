"""A pickle interpreter that builds plain data only and calls nothing except the hooks it is handed.

``pickle.Unpickler`` can be restricted through ``find_class``, but its own machinery stays in reach of the
file: BUILD sets attributes on whatever object the stream names (including the stand-ins ``find_class``
returned, so one file can change how every later file loads), a LONG_BINPUT index sizes the C memo array,
and nothing bounds nesting, stack or memo size. This module interprets the opcode stream itself (decoded by
``pickletools.genops``, the standard library's reference decoder), so that every operation is checked here:

  * globals are resolved by ``Hooks.find_class``; calling one (REDUCE), giving one state (BUILD) and
    persistent ids are delegated to the hooks, which decide what is allowed;
  * opcodes that create instances of named classes (INST, OBJ, NEWOBJ, NEWOBJ_EX), the extension registry
    (EXT1/2/4) and out-of-band buffers are refused;
  * dict keys and set items must be scalars or flat tuples of scalars, so hashing never recurses, and their cost
    is bounded: a tuple key holds at most ``max_key_items`` items (Python re-hashes a tuple on every insertion,
    so a big tuple reused from the memo would cost its length each time), key text at most ``max_key_chars``,
    integer keys lie within ±2**60 (there ``hash(k) == k``, so no two collide; multiples of 2**61 − 1 all hash
    alike and would make a dict quadratic) and keys whose hash the file can choose (floats, tuples) are at most
    ``max_chosen_hash_keys`` per pickle;
  * the pickle's size, one text argument's length, the stack, the MARK nesting, the memo, the number of
    objects and container slots created and each container's length are bounded by ``PickleLimits``; none of
    this code recurses.
"""

from __future__ import annotations

import pickletools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, BinaryIO, Protocol

__all__ = ["MAX_INT_KEY", "Hooks", "PickleLimits", "PickleRejected", "describe", "load"]

MAX_INT_KEY = 1 << 60
"""Integer dict keys and set items must lie in ``[-MAX_INT_KEY, MAX_INT_KEY]``: there ``hash(k) == k`` (except
``hash(-1) == -2``), so a file cannot make many keys collide (CPython hashes ints modulo 2**61 − 1)."""


class PickleRejected(Exception):
    """The stream is malformed, too large or asks for something refused; ``unsafe`` marks the latter."""

    def __init__(self, message: str, *, unsafe: bool = False):
        super().__init__(message)
        self.unsafe = unsafe


@dataclass(frozen=True)
class PickleLimits:
    """Bounds on one pickle; the defaults leave a wide margin over state dicts of 100k tensors.

    Attributes:
        max_bytes: size of the pickle stream itself.
        max_line: one newline-terminated argument of the text opcodes (GLOBAL, INT, STRING, ...).
        max_objects: objects created plus slots filled in containers (each costs tens of bytes).
        max_stack: entries on the stack, counting those below every open MARK.
        max_marks: MARKs open at once.
        max_memo: memo entries.
        max_container: items in one list, tuple, dict or set.
        max_key_items: items of one tuple used as a dict key or set item (each insertion hashes them all).
        max_key_chars: characters (bytes) of one str (bytes) key, alone or in a tuple key.
        max_chosen_hash_keys: insertions of float or tuple keys per pickle, whose hash a file can choose so that
            they all collide (each costs up to the number of keys already there).
    """

    max_bytes: int = 64 << 20
    max_line: int = 1 << 16
    max_objects: int = 1 << 23
    max_stack: int = 1 << 20
    max_marks: int = 1 << 12
    max_memo: int = 1 << 20
    max_container: int = 1 << 20
    max_key_items: int = 16
    max_key_chars: int = 1 << 16
    max_chosen_hash_keys: int = 1 << 10


class Hooks(Protocol):
    """What the caller allows: each hook returns the value to push, or raises ``PickleRejected``."""

    def find_class(self, module: str, name: str) -> Any: ...

    def persistent_load(self, pid: Any) -> Any: ...

    def call(self, func: Any, args: tuple) -> Any: ...

    def build(self, target: Any, state: Any) -> Any: ...


_SCALARS = (type(None), bool, int, float, str, bytes)


def describe(obj: Any, limit: int = 60) -> str:
    """A short, non-recursive description of an untrusted object, safe to put in an error message."""
    if isinstance(obj, int) and not isinstance(obj, bool) and obj.bit_length() > 64:
        return f"an integer of {obj.bit_length()} bits"  # repr of a huge int is slow, or refused past 4300 digits
    if isinstance(obj, (str, bytes)) and len(obj) > limit:
        return repr(obj[:limit]) + "…"
    if isinstance(obj, _SCALARS):
        return repr(obj)
    if isinstance(obj, (list, tuple, dict, set, frozenset)):
        return f"a {type(obj).__name__} of {len(obj)} items"
    return f"a {type(obj).__name__}"


def _key_scalar(value: Any, limits: PickleLimits) -> str | None:
    """Why ``value`` cannot be (part of) a key, or None if it can."""
    if type(value) is int and not -MAX_INT_KEY <= value <= MAX_INT_KEY:
        return f"an integer outside ±2**60 ({describe(value)}), whose hash a file could make collide"
    if isinstance(value, (str, bytes)) and len(value) > limits.max_key_chars:
        return f"a {type(value).__name__} of {len(value)} characters, more than {limits.max_key_chars}"
    if not isinstance(value, _SCALARS):
        return f"{describe(value)}; only scalars and flat tuples of scalars are supported"
    return None


class _BoundedReader:
    """The part of a binary stream that ``pickletools.genops`` reads, with the pickle size bounded."""

    def __init__(self, raw: BinaryIO, limits: PickleLimits):
        self._raw = raw
        self._left = limits.max_bytes
        self._max_line = limits.max_line
        self._consumed = 0

    def _take(self, n: int) -> None:
        if n > self._left:
            raise PickleRejected(f"pickle longer than the limit of {self._consumed + self._left} bytes")

    def read(self, n: int = -1) -> bytes:
        if n < 0:
            raise PickleRejected("unbounded read")
        self._take(n)
        data = self._raw.read(n)
        self._left -= len(data)
        self._consumed += len(data)
        return data

    def readline(self) -> bytes:
        # A text argument longer than max_line is not newline-terminated here, which genops reports as
        # malformed, instead of reading the rest of a (possibly large) file into one line.
        data = self._raw.readline(min(self._max_line, self._left) + 1)
        self._take(len(data))
        self._left -= len(data)
        self._consumed += len(data)
        return data

    def tell(self) -> int:
        return self._consumed


class _Machine:
    def __init__(self, hooks: Hooks, limits: PickleLimits):
        self.hooks = hooks
        self.limits = limits
        self.stack: list[Any] = []
        self.marks: list[list[Any]] = []
        self.memo: dict[int, Any] = {}
        self.created = 0
        self.chosen_hash_keys = 0
        self.depth_total = 0  # entries on the stack plus those held below the open marks

    # -- bookkeeping -------------------------------------------------------------------------------------

    def count(self, n: int = 1) -> None:
        self.created += n
        if self.created > self.limits.max_objects:
            raise PickleRejected(f"more than {self.limits.max_objects} objects and container slots")

    def push(self, value: Any) -> None:
        if self.depth_total >= self.limits.max_stack:
            raise PickleRejected(f"pickle stack deeper than {self.limits.max_stack}")
        self.stack.append(value)
        self.depth_total += 1

    def pop(self) -> Any:
        if not self.stack:
            raise PickleRejected("pickle stack underflow")
        self.depth_total -= 1
        return self.stack.pop()

    def top(self) -> Any:
        if not self.stack:
            raise PickleRejected("pickle stack underflow")
        return self.stack[-1]

    def pop_mark(self) -> list[Any]:
        if not self.marks:
            raise PickleRejected("MARK expected on the pickle stack")
        items = self.stack
        self.depth_total -= len(items)
        self.stack = self.marks.pop()
        return items

    def key(self, key: Any) -> Any:
        """``key`` if it may be a dict key or set item, with bounded hashing cost; else ``PickleRejected``."""
        limits = self.limits
        if type(key) is tuple:
            if len(key) > limits.max_key_items:
                raise PickleRejected(
                    f"dict key or set item is a tuple of {len(key)} items, more than {limits.max_key_items} "
                    "(a tuple is hashed again at every insertion)"
                )
            for item in key:
                why = _key_scalar(item, limits)
                if why is not None:
                    raise PickleRejected(f"dict key or set item is a tuple holding {why}")
        else:
            why = _key_scalar(key, limits)
            if why is not None:
                raise PickleRejected(f"dict key or set item is {why}")
        if type(key) in (tuple, float):
            self.chosen_hash_keys += 1
            if self.chosen_hash_keys > limits.max_chosen_hash_keys:
                raise PickleRejected(
                    f"more than {limits.max_chosen_hash_keys} float or tuple dict keys or set items, whose "
                    "hashes a file can make collide"
                )
        return key

    def fits(self, container: Any, n: int) -> None:
        """Refuses growing ``container`` (or making one) to more than ``max_container`` items."""
        if len(container) + n > self.limits.max_container:
            raise PickleRejected(f"a container of more than {self.limits.max_container} items")

    # -- opcodes -----------------------------------------------------------------------------------------

    def run(self, reader: _BoundedReader) -> Any:
        handlers: dict[str, Callable[[Any], Any]] = {}
        for name in dir(self):
            if name.startswith("op_"):
                handlers[name[3:]] = getattr(self, name)
        try:
            for opcode, arg, pos in pickletools.genops(reader):
                handler = handlers.get(opcode.name)
                if handler is None:
                    raise PickleRejected(
                        f"opcode {opcode.name} at byte {pos} is refused: it creates objects of named classes "
                        "or reaches outside the pickle, which a state dict of tensors never needs",
                        unsafe=True,
                    )
                try:
                    handler(arg)
                except PickleRejected as err:
                    raise PickleRejected(f"{err} (opcode {opcode.name} at byte {pos})", unsafe=err.unsafe) from None
                if opcode.name == "STOP":
                    return self.result
        except (ValueError, EOFError, OverflowError, UnicodeDecodeError) as err:
            # genops reports malformed or truncated arguments as ValueError.
            raise PickleRejected(f"malformed or truncated pickle ({err})") from None
        raise PickleRejected("pickle ended without STOP")  # genops stops only at STOP; kept for safety

    def op_PROTO(self, arg: int) -> None:
        if not 0 <= arg <= 5:
            raise PickleRejected(f"unsupported pickle protocol {arg}")

    def op_FRAME(self, arg: int) -> None:
        pass  # frames only group opcodes for buffering; genops reads through them

    def op_STOP(self, arg: None) -> None:
        self.result = self.pop()

    def op_MARK(self, arg: None) -> None:
        if len(self.marks) >= self.limits.max_marks:
            raise PickleRejected(f"more than {self.limits.max_marks} nested MARKs")
        self.marks.append(self.stack)
        self.stack = []

    def op_POP(self, arg: None) -> None:
        if self.stack:
            self.pop()
        else:
            self.pop_mark()  # the C unpickler treats POP at a mark as POP_MARK

    def op_POP_MARK(self, arg: None) -> None:
        self.pop_mark()

    def op_DUP(self, arg: None) -> None:
        self.push(self.top())

    # constants
    def _const(self, value: Any) -> None:
        self.count()
        self.push(value)

    def op_NONE(self, arg: None) -> None:
        self._const(None)

    def op_NEWTRUE(self, arg: None) -> None:
        self._const(True)

    def op_NEWFALSE(self, arg: None) -> None:
        self._const(False)

    def op_INT(self, arg: int | bool) -> None:
        self._const(arg)

    op_BININT = op_BININT1 = op_BININT2 = op_LONG = op_LONG1 = op_LONG4 = op_INT

    def op_FLOAT(self, arg: float) -> None:
        self._const(float(arg))

    op_BINFLOAT = op_FLOAT

    def op_STRING(self, arg: str) -> None:
        # pickletools decodes these Python 2 byte strings as latin-1; torch.load unpickles them with
        # encoding="utf-8", so re-decode to read the same text torch would.
        self._const(arg.encode("latin-1").decode("utf-8"))

    op_BINSTRING = op_SHORT_BINSTRING = op_STRING

    def op_UNICODE(self, arg: str) -> None:
        self._const(arg)

    op_BINUNICODE = op_SHORT_BINUNICODE = op_BINUNICODE8 = op_UNICODE

    def op_BINBYTES(self, arg: bytes) -> None:
        self._const(bytes(arg))

    op_SHORT_BINBYTES = op_BINBYTES8 = op_BYTEARRAY8 = op_BINBYTES

    # containers
    def op_EMPTY_LIST(self, arg: None) -> None:
        self._const([])

    def op_EMPTY_TUPLE(self, arg: None) -> None:
        self._const(())

    def op_EMPTY_DICT(self, arg: None) -> None:
        self._const({})

    def op_EMPTY_SET(self, arg: None) -> None:
        self._const(set())

    def _tuple(self, n: int) -> None:
        if len(self.stack) < n:
            raise PickleRejected("pickle stack underflow")
        items = tuple(self.stack[len(self.stack) - n :])
        for _ in range(n):
            self.pop()
        self.count(1 + n)
        self.push(items)

    def op_TUPLE1(self, arg: None) -> None:
        self._tuple(1)

    def op_TUPLE2(self, arg: None) -> None:
        self._tuple(2)

    def op_TUPLE3(self, arg: None) -> None:
        self._tuple(3)

    def op_TUPLE(self, arg: None) -> None:
        items = self.pop_mark()
        self.fits(items, 0)
        self.count(1 + len(items))
        self.push(tuple(items))

    def op_LIST(self, arg: None) -> None:
        items = self.pop_mark()
        self.fits(items, 0)
        self.count(1 + len(items))
        self.push(list(items))

    def op_DICT(self, arg: None) -> None:
        items = self.pop_mark()
        if len(items) % 2:
            raise PickleRejected("odd number of items for DICT")
        self.fits((), len(items) // 2)
        self.count(1 + len(items))
        self.push({self.key(items[i]): items[i + 1] for i in range(0, len(items), 2)})

    def op_FROZENSET(self, arg: None) -> None:
        items = self.pop_mark()
        self.fits(items, 0)
        self.count(1 + len(items))
        self.push(frozenset(self.key(k) for k in items))

    def _list_target(self) -> list:
        target = self.top()
        if type(target) is not list:
            raise PickleRejected(f"APPEND to {describe(target)}, not a list", unsafe=True)
        return target

    def op_APPEND(self, arg: None) -> None:
        value = self.pop()
        self.count()
        target = self._list_target()
        self.fits(target, 1)
        target.append(value)

    def op_APPENDS(self, arg: None) -> None:
        items = self.pop_mark()
        self.count(len(items))
        target = self._list_target()
        self.fits(target, len(items))
        target.extend(items)

    def _dict_target(self) -> dict:
        target = self.top()
        if not isinstance(target, dict):  # dict or the OrderedDict returned by a hook
            raise PickleRejected(f"SETITEM on {describe(target)}, not a dict", unsafe=True)
        return target

    def op_SETITEM(self, arg: None) -> None:
        value = self.pop()
        key = self.key(self.pop())
        self.count()
        target = self._dict_target()
        self.fits(target, 1)
        target[key] = value

    def op_SETITEMS(self, arg: None) -> None:
        items = self.pop_mark()
        if len(items) % 2:
            raise PickleRejected("odd number of items for SETITEMS")
        self.count(len(items) // 2)
        target = self._dict_target()
        self.fits(target, len(items) // 2)
        for i in range(0, len(items), 2):
            target[self.key(items[i])] = items[i + 1]

    def op_ADDITEMS(self, arg: None) -> None:
        items = self.pop_mark()
        target = self.top()
        if type(target) is not set:
            raise PickleRejected(f"ADDITEMS to {describe(target)}, not a set", unsafe=True)
        self.count(len(items))
        self.fits(target, len(items))
        target.update(self.key(k) for k in items)

    # memo
    def _put(self, index: int) -> None:
        if index not in self.memo and len(self.memo) >= self.limits.max_memo:
            raise PickleRejected(f"more than {self.limits.max_memo} memo entries")
        self.memo[index] = self.top()

    def op_PUT(self, arg: int) -> None:
        self._put(arg)

    op_BINPUT = op_LONG_BINPUT = op_PUT

    def op_MEMOIZE(self, arg: None) -> None:
        self._put(len(self.memo))

    def op_GET(self, arg: int) -> None:
        try:
            self.push(self.memo[arg])
        except KeyError:
            raise PickleRejected(f"memo entry {describe(arg)} read before it was written") from None

    op_BINGET = op_LONG_BINGET = op_GET

    # delegated to the hooks
    def op_GLOBAL(self, arg: str) -> None:
        module, _, name = arg.partition(" ")
        self.count()
        self.push(self.hooks.find_class(module, name))

    def op_STACK_GLOBAL(self, arg: None) -> None:
        name = self.pop()
        module = self.pop()
        if type(module) is not str or type(name) is not str:
            raise PickleRejected(
                f"STACK_GLOBAL with {describe(module)} and {describe(name)} instead of two strings", unsafe=True
            )
        self.count()
        self.push(self.hooks.find_class(module, name))

    def op_BINPERSID(self, arg: None) -> None:
        pid = self.pop()
        self.count()
        self.push(self.hooks.persistent_load(pid))

    def op_REDUCE(self, arg: None) -> None:
        args = self.pop()
        func = self.pop()
        if type(args) is not tuple:
            raise PickleRejected(f"REDUCE with {describe(args)} as arguments, not a tuple")
        self.count()
        self.push(self.hooks.call(func, args))

    def op_BUILD(self, arg: None) -> None:
        state = self.pop()
        target = self.top()
        self.hooks.build(target, state)


def load(stream: BinaryIO, hooks: Hooks, limits: PickleLimits | None = None) -> Any:
    """Interprets one pickle from ``stream`` (read up to its STOP opcode) and returns the object it builds.

    Args:
        stream: a binary stream positioned at the pickle; left just after its STOP opcode.
        hooks: resolves globals and persistent ids and decides which calls and BUILDs are allowed.
        limits: size bounds; ``PickleLimits()`` when omitted.

    Returns:
        The unpickled object: scalars, ``list``, ``tuple``, ``dict``, ``set``, ``frozenset`` and whatever the
        hooks returned.

    Raises:
        PickleRejected: malformed, truncated or over a limit, or (``unsafe=True``) an operation that could run
            code or change objects outside the pickle.
    """
    return _Machine(hooks, limits or PickleLimits()).run(_BoundedReader(stream, limits or PickleLimits()))
