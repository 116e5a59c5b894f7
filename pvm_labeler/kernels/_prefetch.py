"""A software prefetch for numba kernels (LLVM's ``llvm.prefetch`` intrinsic, lowered to ``prefetcht0``).

Why: the backward SGM sweep walks the forward sums and the cost volume in DESCENDING addresses, 576 bytes per
pixel at D = 192. The hardware prefetcher follows that stream poorly on this machine (AMD Zen 4): reading the
forward sums alone cost 44 ms of the 106-ms backward sweep on a KITTI frame. Asking for the lines a few pixels
ahead removes most of it (backward sweep + WTA 142 -> 99 ms CPU, same results; see docs/sgm.md). A prefetch
is only a hint: it never faults, so an address past the end of an array is harmless.
"""

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

_I8P = ir.IntType(8).as_pointer()
# LLVM >= 15 with opaque pointers names the overload ".p0"; typed-pointer builds (older llvmlite) ".p0i8".
_NAME = "llvm.prefetch.p0" if str(_I8P) == "ptr" else "llvm.prefetch.p0i8"


@intrinsic
def prefetch(typingctx, addr):
    """prefetch(addr): read prefetch, high temporal locality, of the cache line holding the integer address."""
    if not isinstance(addr, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [_I8P, i32, i32, i32])
        fn = builder.module.declare_intrinsic(_NAME, fnty=fnty)
        # (address, rw = 0 read, locality = 3 keep in all levels, cache type = 1 data)
        builder.call(fn, [builder.inttoptr(args[0], _I8P), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return types.void(addr), codegen
