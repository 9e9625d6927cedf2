"""Compiled kernels: numba's ``njit`` with its on-disk cache.

The control stack's arrays are tiny (N <= 35 robots, a few obstacles), so
numpy's per-call overhead, not arithmetic, dominates a control tick; the hot
inner functions are written as loops and compiled. ``cache=True`` stores the
machine code beside the source (``__pycache__``) so a second run pays no
compile time; numba itself falls back to a user-wide cache folder when the
install is read-only (or to ``NUMBA_CACHE_DIR`` when set). Where no folder
is writable at all the kernels are compiled anew in each process.

Floating-point semantics follow numpy's (``error_model="numpy"``: x / 0 is
inf or NaN, not an exception). Kernels are plain functions over float64 arrays: no MuJoCo, no I/O. Each has
one implementation; the public function that calls it checks shapes and
documents units.
"""

from __future__ import annotations

from typing import Any, Callable

import numba
import numpy as np


def kernel(function: Callable) -> Callable:
    """Compile ``function`` in nopython mode with the on-disk cache (without it
    when no cache folder is writable)."""
    try:
        return numba.njit(cache=True, error_model="numpy")(function)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return numba.njit(error_model="numpy")(function)


# The kernels' compiled entry points once the dispatcher has compiled them (``compiled_call``).
_ENTRIES: dict[tuple, Any] = {}


def compiled_call(dispatcher: Any, arguments: tuple, key: tuple) -> Any:
    """``dispatcher(*arguments)``, through its compiled entry point after the first call with this ``key``:
    the dispatcher types every argument at each call, microseconds for a kernel of many arrays. The key
    must fix the signature: the caller passes arrays of one dtype, layout and writeability and scalars of
    one Python type under it (a key per variant, e.g. a caller's read-only array)."""
    entry = _ENTRIES.get(key)
    if entry is not None:
        return entry(*arguments)
    result = dispatcher(*arguments)
    overloads = getattr(dispatcher, "overloads", None)
    if overloads is not None:  # None: numba's JIT disabled
        signature = tuple(dispatcher.typeof_pyval(argument) for argument in arguments)
        if signature in overloads:
            _ENTRIES[key] = overloads[signature].entry_point
    return result


class CompileWatch:
    """Wall time spent compiling kernels while it is open (numba's compile
    events; a kernel loaded from the on-disk cache is no compile). ``on_first``
    is called once, when the first compile starts, so a run can say why its
    first seconds are slow. Use as a context manager, or ``open``/``close``."""

    def __init__(self, on_first: Callable[[], None] | None = None):
        self.on_first = on_first
        self.seconds = 0.0  # wall time inside outermost compiles, s
        self.count = 0  # outermost compiles (a kernel calling kernels compiles them inside its own)
        self._depth = 0
        self._started = 0.0
        self._listener = None

    def open(self) -> "CompileWatch":
        import time

        from numba.core import event

        watch = self

        class _Listener(event.Listener):
            def on_start(self, _event) -> None:
                if watch._depth == 0:
                    if watch.count == 0 and watch.on_first is not None:
                        watch.on_first()
                    watch._started = time.perf_counter()
                watch._depth += 1

            def on_end(self, _event) -> None:
                watch._depth -= 1
                if watch._depth == 0:
                    watch.seconds += time.perf_counter() - watch._started
                    watch.count += 1

        self._listener = _Listener()
        event.register("numba:compile", self._listener)
        return self

    def close(self) -> None:
        if self._listener is not None:
            from numba.core import event

            event.unregister("numba:compile", self._listener)
            self._listener = None

    def __enter__(self) -> "CompileWatch":
        return self.open()

    def __exit__(self, *_exc) -> None:
        self.close()


def generator_pointers(rng) -> tuple[int, int, int, int, int]:
    """What a kernel needs to draw from ``rng`` (a ``numpy.random.Generator``) without being passed it: its
    bit generator's state address and state, and its next_uint64, next_uint32 and next_double function
    addresses, as numba reads them each time a Generator is an argument (three ``ctypes.cast`` calls, about
    15 us a call). They stay valid while ``rng`` lives: keep it."""
    import ctypes

    face = rng.bit_generator.ctypes
    address = [ctypes.cast(function, ctypes.c_void_p).value
               for function in (face.next_uint64, face.next_uint32, face.next_double)]
    return (int(face.state_address), int(face.state.value), *address)


def _generator_at_intrinsic():
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    bit_generator_type = types.NumPyRandomBitGeneratorType("bit_generator")

    @intrinsic
    def generator_at(typingctx, state_address, state, next_uint64, next_uint32, next_double):
        """Inside a kernel: the Generator whose ``generator_pointers`` these are, as numba's unboxing of it
        builds it (the same bit generator state, advanced in place; no Python object behind it)."""
        signature = types.npy_rng(state_address, state, next_uint64, next_uint32, next_double)

        def codegen(context, builder, signature, arguments):
            bits = cgutils.create_struct_proxy(bit_generator_type)(context, builder)
            bits.state_address, bits.state = arguments[0], arguments[1]
            bits.fnptr_next_uint64, bits.fnptr_next_uint32, bits.fnptr_next_double = arguments[2:]
            generator = cgutils.create_struct_proxy(signature.return_type)(context, builder)
            generator.bit_generator = bits._getvalue()
            return generator._getvalue()  # no meminfo, no parent: nothing for the runtime to release

        return signature, codegen

    return generator_at


generator_at = _generator_at_intrinsic()



@kernel
def _pairwise_block(values, start, count):
    """numpy's pairwise summation (``pairwise_sum`` in numpy's loops_utils) of at most 128 values:
    sequential below 8, else eight running sums, combined in pairs, then the rest in order."""
    if count < 8:
        total = 0.0
        for i in range(start, start + count):
            total += values[i]
        return total
    r0, r1, r2, r3 = values[start], values[start + 1], values[start + 2], values[start + 3]
    r4, r5, r6, r7 = values[start + 4], values[start + 5], values[start + 6], values[start + 7]
    i = start + 8
    whole = start + count - count % 8
    while i < whole:
        r0 += values[i]
        r1 += values[i + 1]
        r2 += values[i + 2]
        r3 += values[i + 3]
        r4 += values[i + 4]
        r5 += values[i + 5]
        r6 += values[i + 6]
        r7 += values[i + 7]
        i += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < start + count:
        total += values[i]
        i += 1
    return total


@kernel
def numpy_sum(values):
    """``numpy.add.reduce`` of a contiguous float64 vector, bit for bit (tests/test_compiled.py): inside a
    kernel, a sum that must equal the one numpy would give the same values. Above 128 values numpy
    splits in halves (at a multiple of 8) and adds the halves' sums; that recursion is walked here with a
    stack (numba's on-disk cache cannot link a recursive kernel into another module's)."""
    n = values.shape[0]
    if n <= 128:
        return 0.0 + _pairwise_block(values, 0, n)
    depth = 64  # halves of at least 64 values: far more levels than any array has
    start = np.empty(depth, dtype=np.int64)
    count = np.empty(depth, dtype=np.int64)
    stage = np.zeros(depth, dtype=np.int64)  # 0 left to sum, 1 summing it, 2 right to sum, 3 summing it
    left = np.empty(depth)
    right = np.empty(depth)
    start[0], count[0], stage[0] = 0, n, 0
    top = 1
    total = 0.0
    while top > 0:
        f = top - 1
        if count[f] <= 128:
            done = _pairwise_block(values, start[f], count[f])
        elif stage[f] == 0 or stage[f] == 2:
            half = count[f] // 2
            half -= half % 8
            child = top
            start[child], count[child], stage[child] = (start[f], half, 0) if stage[f] == 0 else (
                start[f] + half, count[f] - half, 0)
            stage[f] += 1
            top += 1
            continue
        else:
            done = left[f] + right[f]
        top -= 1
        if top == 0:
            total = done
        elif stage[top - 1] == 1:
            left[top - 1] = done
            stage[top - 1] = 2
        else:
            right[top - 1] = done
    return 0.0 + total


@kernel
def numpy_sum_where(values, where):
    """(``numpy.add.reduce(values[where])``, ``where``'s count): the sum of the values ``where`` marks
    (bool, as long), bit for bit as numpy sums them once picked out, in one call."""
    picked = np.empty(values.shape[0])
    count = 0
    for i in range(values.shape[0]):
        if where[i]:
            picked[count] = values[i]
            count += 1
    return numpy_sum(picked[:count]), count
