"""File descriptors and the clock from compiled code running without the interpreter lock
(numba intrinsics, compiled into their caller):

- :func:`fd_write`: one ``write`` of bytes of an array;
- :func:`fd_poll`: ``poll`` of one descriptor for reading, with a timeout;
- :func:`errno`: the calling thread's ``errno`` (after a call returned -1);
- :func:`now_ns`: the monotonic clock (``CLOCK_MONOTONIC``, the one ``time.monotonic_ns``
  reads) in nanoseconds.

Each is a call of the C library's function, named in the compiled code and resolved when it
is loaded (so numba's cache keeps it). A call into the C library is also where the compiler
must assume that any memory the caller shares may be read or written: what the caller stored
in a shared array before the call is in memory, and what it reads after the call is read
again, not kept from before.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["CLOCK_MONOTONIC", "EINTR", "errno", "fd_poll", "fd_write", "now_ns"]

#: Linux's ``CLOCK_MONOTONIC`` (``time.CLOCK_MONOTONIC``)
CLOCK_MONOTONIC = 1
#: the error of a call interrupted by a signal (Linux)
EINTR = 4
#: ``poll``'s event "there is data to read"
POLLIN = 0x001
_I8P = ir.IntType(8).as_pointer()
_I16, _I32, _I64 = ir.IntType(16), ir.IntType(32), ir.IntType(64)
_IO = ir.FunctionType(_I64, [_I32, _I8P, _I64])     # ssize_t write(int, void *, size_t)


def _io(name: str):
    def typer(typingctx, fd, arr, start, size):
        if not isinstance(arr, types.Array):
            return None

        def codegen(context, builder, signature, args):
            fd_v, a, at, n = args
            data = builder.bitcast(context.make_array(signature.args[1])(context, builder, a)
                                   .data, _I8P)
            fn = cgutils.get_or_insert_function(builder.module, _IO, name)
            return builder.call(fn, [builder.trunc(fd_v, _I32), builder.gep(data, [at]), n])
        return types.int64(types.int64, arr, types.int64, types.int64), codegen
    typer.__name__ = f"fd_{name}"
    return typer


#: ``fd_write(fd, arr, start, size)``: ``write`` the ``size`` bytes of ``arr``'s data from
#: byte ``start``; returns what ``write`` returns (bytes written, or -1)
fd_write = intrinsic(_io("write"))


@intrinsic
def fd_poll(typingctx, fd, timeout_ms):
    """1 when ``fd`` has data to read (or is closed), 0 when ``timeout_ms`` (-1: none)
    passed first, -1 on an error or a signal."""
    def codegen(context, builder, signature, args):
        fd_v, timeout = args
        pfd = cgutils.alloca_once(builder, ir.LiteralStructType([_I32, _I16, _I16]))
        builder.store(builder.trunc(fd_v, _I32), cgutils.gep_inbounds(builder, pfd, 0, 0))
        builder.store(ir.Constant(_I16, POLLIN), cgutils.gep_inbounds(builder, pfd, 0, 1))
        builder.store(ir.Constant(_I16, 0), cgutils.gep_inbounds(builder, pfd, 0, 2))
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(_I32, [pfd.type, _I64, _I32]), "poll")
        r = builder.call(fn, [pfd, ir.Constant(_I64, 1), builder.trunc(timeout, _I32)])
        return builder.sext(r, _I64)
    return types.int64(types.int64, types.int64), codegen


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


@intrinsic
def errno(typingctx):
    """The calling thread's ``errno``."""
    def codegen(context, builder, signature, args):
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(_I32.as_pointer(), []), "__errno_location")
        return builder.sext(builder.load(builder.call(fn, [])), _I64)
    return types.int64(), codegen
