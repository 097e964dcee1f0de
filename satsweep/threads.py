"""Independent tasks run by a few threads: for work that releases the GIL (OpenCV, numpy)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Sequence


def map_in_threads(function: Callable[[Any], Any], items: Sequence[Any], *, max_threads: int,
                   name: str) -> list[Any]:
    """``[function(x) for x in items]``, run by up to ``max_threads`` threads (no more than the
    items or the CPUs; one: no thread at all), named ``satsweep-<name>``. The results are in the
    items' order, each the one the sequential loop gives when the tasks are independent."""
    workers = max(1, min(len(items), os.cpu_count() or 1, max_threads))
    if workers == 1:
        return [function(x) for x in items]
    with ThreadPoolExecutor(workers, thread_name_prefix=f"satsweep-{name}") as pool:
        return list(pool.map(function, items))
