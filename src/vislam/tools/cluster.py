"""The batch engine: Dask (``dask.distributed``) clusters, and an in-process stand-in.

:func:`open_engine` is a context manager yielding an engine with ``submit(fn, *args)``
(returning a future with ``.result()``) and ``as_completed(futures)``:

* ``scheduler="tcp://HOST:PORT"`` connects to a running Dask scheduler (started by hand
  with ``dask scheduler`` / ``dask worker``, by dask-jobqueue on a batch system, by the
  Dask Kubernetes operator, ...): the same command scales from a laptop to a cluster
  with no code change;
* otherwise a :class:`distributed.LocalCluster` is started on this machine with
  ``workers`` worker processes of one thread each (the filter is single-threaded by
  design) and no dashboard when the first task is submitted (a command that stops on
  its inputs starts none), and stopped when the block is left — also on an error or
  Ctrl-C;
* ``workers=0`` (or :class:`SequentialEngine` directly) runs every task in this process,
  lazily, in the order the results are asked for: no Dask at all.

Worker processes limit BLAS/OpenMP to one thread (environment variables set before the
worker starts, and :func:`single_thread` around each task).

**Running on a cluster.** The tasks are functions of ``vislam``, so every worker needs
vislam importable (the same version as the client: install it in the workers'
environment, or start the workers with ``PYTHONPATH`` pointing at the same source), and
every path a task reads or writes must be visible on the workers under the same absolute
path: the datasets and ground-truth files of a sweep (``vislam sweep`` resolves the
SPEC's relative paths against the SPEC's folder before sending them), and, for
``vislam report``, the data folder *and* the output folder (report tasks write their run
folders directly into the output's staging directory). On one machine that is automatic;
on a cluster put both on a shared file system (NFS, Lustre, a Kubernetes volume mounted
at the same path in every pod). ``vislam sweep`` writes ``results.csv`` from the client
only, so its ``--out`` needs no sharing. Example, by hand on one machine::

    dask scheduler --host 127.0.0.1 --port 8786 &
    dask worker tcp://127.0.0.1:8786 --nthreads 1 &
    dask worker tcp://127.0.0.1:8786 --nthreads 1 &
    vislam sweep spec.yaml --out sweep-out --scheduler tcp://127.0.0.1:8786
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Any, Callable, Iterable, Iterator

from vislam.errors import ClusterError, ConfigError

__all__ = ["SequentialEngine", "DaskEngine", "open_engine", "single_thread", "WORKER_ENV",
           "DEFAULT_WORKERS", "CONNECT_TIMEOUT_S"]

logger = logging.getLogger(__name__)

#: Worker processes of the default LocalCluster (this project's machines have 2 cores).
DEFAULT_WORKERS = 2
#: How long to wait for a scheduler given by address.
CONNECT_TIMEOUT_S = 20
#: Environment of the LocalCluster's worker processes: single-threaded BLAS/OpenMP.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1", "MPLBACKEND": "Agg"}


def single_thread(fn: Callable, *args, **kwargs):
    """Call ``fn`` with BLAS limited to one thread (how every task runs)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return fn(*args, **kwargs)


def _task(fn: Callable, log_level: int, *args, **kwargs):
    """How a task runs on a worker: single-threaded BLAS, and vislam's log level of the
    client (so e.g. ``--quiet`` also silences the warnings of runs on the workers)."""
    logging.getLogger("vislam").setLevel(log_level)
    return single_thread(fn, *args, **kwargs)


class _Lazy:
    """A 'future' of :class:`SequentialEngine`: computed when its result is asked for."""

    def __init__(self, fn, args, kwargs):
        self._call = (fn, args, kwargs)
        self._done = False
        self._value: Any = None
        self._error: BaseException | None = None

    def result(self):
        if not self._done:
            fn, args, kwargs = self._call
            args = [a.result() if isinstance(a, _Lazy) else a for a in args]
            kwargs = {k: v.result() if isinstance(v, _Lazy) else v for k, v in kwargs.items()}
            try:
                self._value = fn(*args, **kwargs)
            except Exception as exc:  # re-raised on every .result(), like a Dask future
                self._error = exc
            self._done = True
            self._call = None
        if self._error is not None:
            raise self._error
        return self._value


class SequentialEngine:
    """Runs tasks in this process, one at a time, when their results are asked for."""

    name = "sequential (this process)"
    n_workers = 1

    def submit(self, fn: Callable, *args, **kwargs) -> _Lazy:
        kwargs.pop("priority", None)
        return _Lazy(fn, args, kwargs)

    def as_completed(self, futures: Iterable[_Lazy]) -> Iterator[_Lazy]:
        for f in futures:
            with contextlib.suppress(Exception):
                f.result()
            yield f

    def cancel(self, futures) -> None:
        pass


class DaskEngine:
    """Tasks on a Dask cluster through ``client`` (a :class:`distributed.Client`)."""

    def __init__(self, client, name: str):
        self.client = client
        self.name = name

    @property
    def n_workers(self) -> int:
        try:
            return len(self.client.scheduler_info().get("workers", {}))
        except Exception:  # pragma: no cover - informational only
            return 0

    def submit(self, fn: Callable, *args, priority: int = 0, **kwargs):
        level = logging.getLogger("vislam").getEffectiveLevel()
        return self.client.submit(_task, fn, level, *args, pure=False, priority=priority, **kwargs)

    def as_completed(self, futures):
        from distributed import as_completed

        return as_completed(list(futures))

    def cancel(self, futures) -> None:
        with contextlib.suppress(Exception):
            self.client.cancel(list(futures))


@contextlib.contextmanager
def open_engine(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """The engine of a command (see the module docstring). ``workers`` is the number of
    LocalCluster workers (default :data:`DEFAULT_WORKERS`; 0: run in this process); it
    is ignored with ``scheduler`` (the cluster has its own workers). A scheduler that
    cannot be reached is a ClusterError here; a local cluster starts with the first
    task, and one that cannot start is a ClusterError there."""
    if workers is not None and workers < 0:
        raise ConfigError(f"--workers must be >= 0, got {workers}")
    if scheduler is None and workers == 0:
        yield SequentialEngine()
        return
    if scheduler is not None:
        from distributed import Client

        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ClusterError(f"--scheduler {scheduler}: cannot connect to a Dask scheduler there: "
                              f"{' '.join(str(exc).split()) or type(exc).__name__}") from None
        with client:
            engine = DaskEngine(client, f"Dask scheduler {scheduler}")
            logger.info("connected to %s (%d workers)", scheduler, engine.n_workers)
            yield engine
        return
    n = DEFAULT_WORKERS if workers is None else workers
    with contextlib.ExitStack() as stack:
        engine = _DeferredEngine(lambda: stack.enter_context(_local_cluster(n)),
                                 f"local Dask cluster, {n} worker processes")
        yield engine


class _DeferredEngine:
    """The engine of a local cluster that starts with the first task: a command that
    stops on its inputs (a missing or broken dataset, nothing to run) starts no worker
    processes (about 1 s each here). ``start`` enters the cluster's context on the
    stack of :func:`open_engine`, which stops it when the block is left."""

    def __init__(self, start: Callable[[], "DaskEngine"], name: str):
        self._start = start
        self._engine: DaskEngine | None = None
        self.name = name

    def _started(self) -> "DaskEngine":
        if self._engine is None:
            self._engine = self._start()
        return self._engine

    @property
    def n_workers(self) -> int:
        return self._started().n_workers

    def submit(self, fn: Callable, *args, **kwargs):
        return self._started().submit(fn, *args, **kwargs)

    def as_completed(self, futures):
        return self._started().as_completed(futures)

    def cancel(self, futures) -> None:
        if self._engine is not None:
            self._engine.cancel(futures)


@contextlib.contextmanager
def _local_cluster(n: int) -> Iterator["DaskEngine"]:
    """A LocalCluster of ``n`` single-threaded worker processes and its client."""
    from distributed import Client, LocalCluster

    saved = {k: os.environ.get(k) for k in WORKER_ENV}
    os.environ.update(WORKER_ENV)  # inherited by the spawned worker processes
    try:
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                               host="127.0.0.1", env=dict(WORKER_ENV))
    except (OSError, RuntimeError, TimeoutError) as exc:
        cause = exc.__cause__ or exc
        raise ClusterError(f"cannot start a local Dask cluster with {n} worker processes: "
                           f"{' '.join(str(cause).split()) or type(cause).__name__} (--sequential runs without Dask)"
                           ) from None
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    with cluster, Client(cluster) as client:
        logger.info("started a local Dask cluster with %d worker processes", n)
        yield DaskEngine(client, f"local Dask cluster, {n} worker processes")
