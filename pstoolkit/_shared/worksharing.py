"""Tasks taken as threads come free in numba's parallel loops.

``numba.prange`` gives each thread one contiguous share of the iterations, fixed before the loop
starts (the OpenMP layer's static schedule; ``numba.parallel_chunksize`` only cuts the shares into
chunks, still dealt out in that order). Where the work per iteration varies with its place — event
pixels of a bright, busy part of an image next to a dark one — one thread ends long before the
other. A ``prange`` over the number of threads, in which each thread takes the next task from a
shared counter (``take_task``) until none is left, balances it: the 256×256 sphere's blocks had one
thread idle for up to a quarter of a block with ``prange`` over the tasks. The number of threads is
best passed in (``numba.get_num_threads()`` from Python): compiled code that calls it cannot be
cached.
"""

from __future__ import annotations

from typing import Any

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def take_task(typingctx: Any, counter: types.Array) -> tuple[Any, Any]:
    """``counter[0]`` before adding one to it, as one atomic step (for compiled code): each call, from
    any thread, gets a different number, 0, 1, 2, … in the order the calls reach it. ``counter`` is
    a 1-d int64 array of at least one element, zero before the first task. numba does not see the
    call write ``counter`` (a call's array arguments count as read): in a ``parallel=True`` function
    it may move a read of ``counter`` that follows a parallel loop ahead of that loop, so read the
    count after the loop only outside compiled code."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1):
        return None

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        array_type = signature.args[0]
        array = context.make_array(array_type)(context, builder, args[0])
        slot = cgutils.get_item_pointer(context, builder, array_type, array, [context.get_constant(types.intp, 0)])
        return builder.atomic_rmw("add", slot, context.get_constant(types.int64, 1), "monotonic")

    return types.int64(counter), codegen
