"""Work units run in worker processes: one per core by default, at most one per unit.

Each unit is ``fn(*args)`` with torch limited to its share of the cores. Workers are
spawned (a fresh interpreter each), so ``fn`` must be a module-level function and a script
that starts a pool must guard its entry point with ``if __name__ == "__main__":``. Results
come back in the order of the units, whatever the number of workers.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Callable, Sequence

from quadformer.io import set_threads


def _call(fn: Callable[..., Any], threads: int, args: tuple) -> Any:
    set_threads(threads)
    return fn(*args)


def run_jobs(fn: Callable[..., Any], units: Sequence[tuple], workers: int | None = None, progress: bool = True,
             desc: str = "work", unit: str = "unit") -> list[Any]:
    """``[fn(*u) for u in units]`` in ``workers`` processes, with a progress bar."""
    if not units:
        return []
    workers = workers or min(len(units), os.cpu_count() or 1)
    threads = max(1, (os.cpu_count() or 1) // workers)
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(units), desc=desc, unit=unit)
    out: list[Any] = []
    try:
        if workers == 1:
            for u in units:
                out.append(_call(fn, threads, u))
                if bar is not None:
                    bar.update(1)
        else:
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                futures = [pool.submit(_call, fn, threads, u) for u in units]
                for fut in futures:
                    out.append(fut.result())
                    if bar is not None:
                        bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return out
