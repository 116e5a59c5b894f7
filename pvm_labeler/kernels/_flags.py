"""The one place that sets the numba fastmath flags of every labeler kernel.

``nnan`` and ``ninf`` are deliberately left out: NaN marks "no disparity" in every float32 map, and with those
flags LLVM may fold ``x != x`` to False and silently drop the sentinel. A test can monkeypatch ``FASTMATH`` to an
empty set before the kernels compile (NUMBA_DISABLE_JIT runs ignore it anyway).
"""

FASTMATH: set[str] = {"nsz", "arcp", "contract", "afn", "reassoc"}
