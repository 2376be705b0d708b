"""What a compiled loop running without the interpreter lock needs to hand its results to a
Python thread as it goes: the call's side of a :class:`~dentibot.app.relay.Relay`
(:func:`begin`, :func:`hold` before each tick, :func:`publish` after it, :func:`end`), on
three numba intrinsics, compiled into the caller:

- :func:`post`: one 8-byte write to a file descriptor (an ``eventfd``, or a pipe), which
  wakes a thread blocked reading it;
- :func:`wait`: one 8-byte read from a file descriptor, which blocks until something is
  posted there;
- :func:`now_ns`: the monotonic clock (``CLOCK_MONOTONIC``, the one ``time.monotonic_ns``
  reads) in nanoseconds.

Each is a call of the C library's function, named in the compiled code and resolved when it
is loaded (so numba's cache keeps it). A call into the C library is also where the compiler
must assume that any memory the loop shares may be read or written: a number the loop stored
in a shared array before :func:`post` is in memory when the other thread wakes, and a number
read after :func:`wait` is read again, not kept from before.
"""

from __future__ import annotations

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["ABORT", "CLOCK_MONOTONIC", "CTL_SIZE", "LIMIT", "PUB", "TAIL_NS", "begin", "end", "hold",
           "now_ns", "post", "publish", "wait"]

#: Linux's ``CLOCK_MONOTONIC`` (``time.CLOCK_MONOTONIC``)
CLOCK_MONOTONIC = 1
_I8P = ir.IntType(8).as_pointer()
_I32, _I64 = ir.IntType(32), ir.IntType(64)
_IO = ir.FunctionType(_I64, [_I32, _I8P, _I64])     # ssize_t read/write(int, void *, size_t)


def _io(name: str):
    def typer(typingctx, fd, word):
        if not isinstance(word, types.Array) or word.dtype.bitwidth != 64:
            return None

        def codegen(context, builder, signature, args):
            fd_v, arr = args
            data = context.make_array(signature.args[1])(context, builder, arr).data
            fn = cgutils.get_or_insert_function(builder.module, _IO, name)
            return builder.call(fn, [builder.trunc(fd_v, _I32), builder.bitcast(data, _I8P),
                                     ir.Constant(_I64, 8)])
        return types.int64(types.int64, word), codegen
    typer.__name__ = name
    return typer


#: ``post(fd, word)``: write ``word[0]`` (8 bytes, a 64-bit array's first element) to ``fd``;
#: returns what ``write`` returns (8, or -1 on an error)
post = intrinsic(_io("write"))
#: ``wait(fd, word)``: read 8 bytes from ``fd`` into ``word[0]``, blocking until there are;
#: returns what ``read`` returns (8, or -1 on an error or a signal)
wait = intrinsic(_io("read"))


@intrinsic
def now_ns(typingctx):
    """The monotonic clock in ns."""
    def codegen(context, builder, signature, args):
        spec = cgutils.alloca_once(builder, ir.LiteralStructType([_I64, _I64]))
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(_I32, [_I32, spec.type]), "clock_gettime")
        builder.call(fn, [ir.Constant(_I32, CLOCK_MONOTONIC), spec])
        sec = builder.load(cgutils.gep_inbounds(builder, spec, 0, 0))
        nsec = builder.load(cgutils.gep_inbounds(builder, spec, 0, 1))
        return builder.add(builder.mul(sec, ir.Constant(_I64, 1_000_000_000)), nsec)
    return types.int64(), codegen


# ---------------------------------------------------------------------- a call's side
#: ``ctl``'s cells (:class:`~dentibot.app.relay.Relay`): ticks published by the call, ticks
#: it may run (it waits before tick ``ctl[LIMIT]``), nonzero when it must stop, the compute
#: time (ns) of its ticks after the last group published; then the call's own bookkeeping:
#: the current group's compute time so far and when its current stretch began
PUB, LIMIT, ABORT, TAIL_NS, BUSY_NS, STRETCH_T0 = range(6)
CTL_SIZE = 6


@njit(cache=True)
def begin(relay) -> None:
    """At the call's start."""
    on, _, ctl = relay[0], relay[1], relay[2]
    if on:
        ctl[BUSY_NS] = 0
        ctl[STRETCH_T0] = now_ns()


@njit(cache=True)
def hold(relay, i) -> bool:
    """Before tick ``i``: wait while the relay is a group behind; False when the call must
    stop (the relay failed)."""
    on, ctl, granted, word_in = relay[0], relay[2], relay[5], relay[7]
    if not on or i < ctl[LIMIT]:
        return True
    t = now_ns()
    ctl[BUSY_NS] += t - ctl[STRETCH_T0]
    while i >= ctl[LIMIT] and ctl[ABORT] == 0:
        wait(granted, word_in)
    ctl[STRETCH_T0] = now_ns()
    return ctl[ABORT] == 0


@njit(cache=True)
def publish(relay, i) -> None:
    """After tick ``i``'s row is written: publish the group it completes, if it does."""
    on, every, ctl, busy, posted, word_out = (relay[0], relay[1], relay[2], relay[3],
                                              relay[4], relay[6])
    if not on or (i + 1) % every != 0:
        return
    t = now_ns()
    busy[(i + 1) // every - 1] = ctl[BUSY_NS] + t - ctl[STRETCH_T0]
    ctl[BUSY_NS] = 0
    ctl[STRETCH_T0] = t
    ctl[PUB] = i + 1
    post(posted, word_out)


@njit(cache=True)
def end(relay) -> None:
    """At the call's end: the compute time of the ticks after the last group."""
    on, ctl = relay[0], relay[2]
    if on:
        ctl[TAIL_NS] = ctl[BUSY_NS] + now_ns() - ctl[STRETCH_T0]
