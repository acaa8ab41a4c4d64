"""Work units run on a backend: worker processes of this machine, or Ray tasks on a cluster.

Each unit is ``fn(*args)`` with torch limited to its share of the cores. ``run_jobs`` is the
one entry point; the drivers (detection, resilience, caches) do not know which backend runs
their units, and results come back in the order of the units whatever the backend and the
number of workers.

- ``local`` (default): ``workers`` processes of this machine (one per core by default, at
  most one per unit), each with ``cores // workers`` torch threads. Workers are spawned (a
  fresh interpreter each), so ``fn`` must be a module-level function and a script that starts
  a pool must guard its entry point with ``if __name__ == "__main__":``.
- ``ray``: one Ray task per unit (``ray.remote`` with ``num_cpus`` = the unit's torch threads,
  and ``num_gpus`` for units that train on a GPU), on the cluster at ``address`` (``auto``:
  the one started with ``ray start`` on this machine; ``ray://host:port``: a remote one) or
  on a Ray runtime started here when there is none. Ray is an optional dependency
  (``pip install 'quadformer[ray]'``).

One progress bar counts finished units, in whatever order they finish; each unit's duration,
measured in its worker, is logged at DEBUG level on this module's logger (``unit_desc``,
``unit_label`` and ``unit_seconds`` on the record; ``benchmarks/sweep.py`` reads them). A unit that raises
does not stop the others: every unit runs to its end, then ``UnitError`` names the failed
ones (their labels: configuration, seed, method). Units that write caches keep what they
wrote, so running again does only what is missing.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import re
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from quadformer.io import set_threads

BACKENDS = ("local", "ray")
RAY_INSTALL = "pip install 'quadformer[ray]'"
_ADDRESS = re.compile(r"^(auto|ray://[^\s:/]+:\d+|[^\s:/]+:\d+)$")
log = logging.getLogger(__name__)


class BackendError(RuntimeError):
    """A backend that cannot run: Ray not installed, a cluster out of reach, a bad address."""


class UnitError(RuntimeError):
    """Work units that raised; ``failures`` holds (label, exception) of each."""

    def __init__(self, desc: str, failures: list[tuple[str, BaseException]], total: int) -> None:
        self.failures = failures
        lines = [f"  - {label}: {type(e).__name__}: {_first_line(e)}" for label, e in failures[:10]]
        if len(failures) > 10:
            lines.append(f"  ... and {len(failures) - 10} more")
        super().__init__(f"{desc}: {len(failures)} of {total} work unit(s) failed (the other units' results are "
                         "kept in the cache; running again does only what is missing):\n" + "\n".join(lines))


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else "(no message)"


@dataclass(frozen=True)
class Backend:
    """Where work units run.

    kind: ``local`` (processes of this machine) or ``ray``.
    address: Ray only; ``auto`` (a cluster started with ``ray start`` here), ``ray://host:port``
        or ``host:port``; None: connect to a runtime already started in this process, or start
        one on this machine.
    threads: Ray only; torch threads, and Ray CPUs, per unit (the local pool shares the cores
        among its workers instead).
    gpu_share: Ray only; the share of a GPU a unit that trains on a GPU asks for (0.25: four
        trainings per GPU at once).
    """
    kind: str = "local"
    address: str | None = None
    threads: int = 1
    gpu_share: float = 0.25

    def __post_init__(self) -> None:
        if self.kind not in BACKENDS:
            raise ValueError(f"backend: unknown choice {self.kind!r}; choose from {', '.join(BACKENDS)}")
        if self.address is not None:
            if self.kind != "ray":
                raise ValueError(f"address: only with the ray backend (got --address {self.address!r} with "
                                 f"backend {self.kind!r})")
            if not _ADDRESS.match(self.address):
                raise ValueError(f"address: expected auto, ray://host:port or host:port, got {self.address!r}")
        if self.threads < 1:
            raise ValueError(f"threads: must be at least 1, got {self.threads}")
        if not 0.0 < self.gpu_share <= 1.0:
            raise ValueError(f"gpu_share: must be in (0, 1], got {self.gpu_share}")


LOCAL = Backend()


def _call(fn: Callable[..., Any], threads: int, args: tuple) -> tuple[Any, float]:
    """``fn(*args)`` with ``threads`` torch threads and as many BLAS threads (numpy's SVD of
    PCA, for instance: workers that each start one BLAS thread per core oversubscribe the
    machine, several times slower); returns (result, seconds it took)."""
    set_threads(threads)
    t0 = time.perf_counter()
    with _blas_threads(threads):
        out = fn(*args)
    return out, time.perf_counter() - t0


def _exit_with_parent(parent: int) -> None:
    """Worker initializer: on Linux, the worker receives SIGTERM when the process that started
    it dies (``prctl(PR_SET_PDEATHSIG)``), so a driver killed by a signal does not leave its
    workers computing; elsewhere nothing (a killed driver's workers finish their unit, then
    exit)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)   # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):      # pragma: no cover - no prctl in this libc
        return
    if os.getppid() != parent:             # the driver died before the request took effect
        os._exit(1)


def _blas_threads(threads: int):
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:      # pragma: no cover - installed with scikit-learn
        import contextlib
        return contextlib.nullcontext()
    return threadpool_limits(limits=threads, user_api="blas")


class SharedBar:
    """One progress bar over the work units of several phases (``run_jobs`` calls given it as
    ``progress`` advance it instead of opening bars of their own); the postfix names the phase."""

    def __init__(self, total: int, desc: str = "work", unit: str = "unit") -> None:
        from tqdm.auto import tqdm
        self.bar = tqdm(total=total, desc=desc, unit=unit)

    def phase(self, name: str) -> None:
        self.bar.set_postfix_str(name)

    def update(self, n: int = 1) -> None:
        self.bar.update(n)

    def close(self) -> None:
        self.bar.close()


def run_jobs(fn: Callable[..., Any], units: Sequence[tuple], workers: int | None = None,
             progress: bool | SharedBar = True,
             desc: str = "work", unit: str = "unit", backend: Backend | None = None,
             labels: Sequence[str] | None = None, gpus: float | Sequence[float] = 0.0) -> list[Any]:
    """``[fn(*u) for u in units]`` on ``backend`` (default: local processes), with one progress bar
    (``progress`` a ``SharedBar``: that bar, advanced by this call's units).

    workers: local processes (default one per core); for a Ray runtime started here, its CPUs.
    labels: what each unit is, for the error naming failed units (default: its index).
    gpus: Ray only; GPUs each unit asks for (one number for all, or one per unit).
    Raises ``UnitError`` after every unit has run when any raised."""
    backend = backend or LOCAL
    units = list(units)
    if not units:
        return []
    labels = [f"unit {i}" for i in range(len(units))] if labels is None else list(labels)
    if len(labels) != len(units):
        raise ValueError(f"labels: one per unit needed, got {len(labels)} for {len(units)} units")
    gpu = [float(gpus)] * len(units) if isinstance(gpus, (int, float)) else [float(g) for g in gpus]
    if len(gpu) != len(units):
        raise ValueError(f"gpus: one per unit needed, got {len(gpu)} for {len(units)} units")
    bar = None
    if isinstance(progress, SharedBar):
        bar = progress
        bar.phase(desc)
    elif progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(units), desc=desc, unit=unit)
    try:
        if backend.kind == "ray":
            done, failed = _run_ray(fn, units, backend, workers, gpu, bar)
        else:
            done, failed = _run_local(fn, units, workers, bar)
    finally:
        if bar is not None and bar is not progress:
            bar.close()
    out = []
    for label, d in zip(labels, done):
        result, seconds = d if d is not None else (None, None)
        out.append(result)
        if seconds is not None:
            log.debug("%s: %s took %.2f s", desc, label, seconds,
                      extra={"unit_desc": desc, "unit_label": label, "unit_seconds": seconds})
    if failed:
        failures = [(labels[i], e) for i, e in sorted(failed.items())]
        raise UnitError(desc, failures, len(units)) from failures[0][1]
    return out


def _run_local(fn, units, workers, bar) -> tuple[list[Any], dict[int, BaseException]]:
    workers = workers or min(len(units), os.cpu_count() or 1)
    threads = max(1, (os.cpu_count() or 1) // workers)
    out: list[Any] = [None] * len(units)
    failed: dict[int, BaseException] = {}
    if workers == 1:
        for i, u in enumerate(units):
            try:
                out[i] = _call(fn, threads, u)
            except Exception as e:
                failed[i] = e
            if bar is not None:
                bar.update(1)
        return out, failed
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_exit_with_parent,
                               initargs=(os.getpid(),))
    try:
        futures = {pool.submit(_call, fn, threads, u): i for i, u in enumerate(units)}
        for fut in as_completed(futures):
            i = futures[fut]
            try:
                out[i] = fut.result()
            except Exception as e:
                failed[i] = e
            if bar is not None:
                bar.update(1)
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    return out, failed


def ray_module():
    """The ``ray`` package, or ``BackendError`` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise BackendError(f"the ray backend needs Ray, which is not installed: {RAY_INSTALL} "
                           "(or run with --backend local)") from None
    return ray


def connect(backend: Backend, workers: int | None = None):
    """Ray, connected to the backend's cluster (or to a runtime started here)."""
    ray = ray_module()
    if ray.is_initialized():
        return ray
    try:
        if backend.address is None:
            ray.init(num_cpus=workers, include_dashboard=False, logging_level=logging.WARNING)
        else:
            ray.init(address=backend.address, logging_level=logging.WARNING)
    except Exception as e:   # ConnectionError, RuntimeError, ValueError depending on what is wrong
        where = f"at {backend.address}" if backend.address else "on this machine"
        raise BackendError(f"cannot start or reach a Ray cluster {where}: {type(e).__name__}: {_first_line(e)}"
                           ) from None
    return ray


def cluster_gpus(backend: Backend, workers: int | None = None) -> float:
    """GPUs of the Ray cluster (0 when it has none)."""
    return float(connect(backend, workers).cluster_resources().get("GPU", 0.0))


_REMOTE: dict[str, Any] = {}


def _run_ray(fn, units, backend: Backend, workers, gpu, bar) -> tuple[list[Any], dict[int, BaseException]]:
    ray = connect(backend, workers)
    from ray.exceptions import RayError, RayTaskError

    remote = _REMOTE.get("call")
    if remote is None:
        remote = _REMOTE["call"] = ray.remote(_call)
    refs = {remote.options(num_cpus=backend.threads, num_gpus=g).remote(fn, backend.threads, u): i
            for i, (u, g) in enumerate(zip(units, gpu))}
    out: list[Any] = [None] * len(units)
    failed: dict[int, BaseException] = {}
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                i = refs[ref]
                try:
                    out[i] = ray.get(ref)
                except RayTaskError as e:    # the unit raised: its own exception
                    failed[i] = e.cause if isinstance(getattr(e, "cause", None), BaseException) else e
                except RayError as e:        # the worker died, ran out of memory, ...
                    failed[i] = e
                if bar is not None:
                    bar.update(1)
    except BaseException:
        for ref in pending:
            ray.cancel(ref)
        raise
    return out, failed
