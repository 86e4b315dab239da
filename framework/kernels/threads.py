"""Run a compiled loop over rows (Gaussians, image planes) on every CPU thread torch may use: the rows split into
contiguous chunks, all but the last on a small thread pool, the last on the calling thread.

Why threads and not processes: the loops (`framework.kernels.skin_weights`, `framework.kernels.skinning`,
`framework.kernels.ssim`) are numba functions compiled with `nogil=True`, so two threads run them on two cores
with no copies. The pool is created on first use and forgotten in a forked child (a data-loader worker inherits the
pool object but not its threads, and would wait on them forever).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

#: below this many rows per chunk a second thread costs more than it gains (tests lower it to force several chunks)
MIN_CHUNK = 1024

_pool: ThreadPoolExecutor | None = None


def _forget_pool() -> None:
    global _pool
    _pool = None


os.register_at_fork(after_in_child=_forget_pool)


def row_chunks(n: int, min_chunk: int | None = None) -> list[tuple[int, int]]:
    """[start, stop) ranges of n rows, one per thread torch may use, none shorter than min_chunk (default MIN_CHUNK;
    but at least one range)."""
    parts = max(1, min(torch.get_num_threads(), n // max(1, MIN_CHUNK if min_chunk is None else min_chunk)))
    edges = np.linspace(0, n, parts + 1).astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def run_chunked(
    kernel: Callable[..., None], args_before: tuple, args_after: tuple, n: int, min_chunk: int | None = None
) -> None:
    """kernel(*args_before, start, stop, *args_after) over `row_chunks(n, min_chunk)`, the first chunks on worker
    threads."""
    global _pool
    chunks = row_chunks(n, min_chunk)
    if len(chunks) == 1:
        kernel(*args_before, 0, n, *args_after)
        return
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=max(1, torch.get_num_threads() - 1), thread_name_prefix="compiled")
    futures = [_pool.submit(kernel, *args_before, a, b, *args_after) for a, b in chunks[:-1]]
    a, b = chunks[-1]
    kernel(*args_before, a, b, *args_after)
    for f in futures:
        f.result()
