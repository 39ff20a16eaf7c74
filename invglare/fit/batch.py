"""Many fits on Dask: a cluster of worker processes, one task per photo, failures isolated.

``invglare fit-batch`` hands this module a list of :class:`Task` s (a photo's name, its
report folder and what the work function needs) and a work function that fits one
group of photos on a worker and writes their reports. This module:

- starts a ``LocalCluster`` (:func:`dask_client`): worker processes with one thread each,
  as many as cores, started with ``spawn`` (JAX warns that ``fork`` after its threads
  start can deadlock), each pinned to a core of its own with XLA's thread flags set to
  one thread, so that workers do not compete for cores; or connects to an existing
  scheduler by address, failing within seconds when none answers;
- sets every worker up once (:class:`JaxWorkerSetup`): JAX's persistent compilation cache,
  and XLA's buffers kept mapped (as the ``invglare`` command does). A worker keeps its
  compiled programs between tasks (:mod:`invglare.fit.solve` caches the solve per model
  structure, and the residual function holds no photo-specific static value), so it
  compiles a fit config once and reuses it for every photo of the same size;
- skips photos whose report folder already holds a fit result (:func:`finished`), so an
  interrupted batch resumes where it stopped; reports are written atomically (a whole
  folder at a time, :func:`invglare.files.atomic.atomic_directory`), so a killed run
  never leaves a half-written one, and what it left is completed or removed first
  (:func:`recover_unfinished`);
- submits one task per group of photos (one photo, or up to K same-size photos for a
  vmapped solve) and collects the outcomes as they finish, with a progress bar over
  photos (:func:`run_tasks`). A photo that fails is recorded with its reason and the
  others go on; a worker that dies is replaced by its nanny and its task rerun on another
  worker (Dask retries a task whose worker died up to
  ``distributed.scheduler.allowed-failures`` times, 3 by default).

**Example:**

```python
with dask_client(n_workers=2) as client:
    outcomes = run_tasks(client, [[task] for task in tasks], work)
```
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import re
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from invglare.errors import ConfigError, InputDataError
from invglare.fit.result import FitResult

log = logging.getLogger("invglare")

#: Seconds to wait for an existing scheduler to answer, and then for a first worker.
CONNECT_TIMEOUT_S = 10.0
#: XLA flags of a LocalCluster's workers: one thread each (the cluster has one worker
#: per core, so the cores are already in use).
SINGLE_THREAD_XLA = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
#: Where workers keep JAX's persistent compilation cache unless told otherwise.
DEFAULT_CACHE_DIR = Path.home() / ".cache" / "invglare" / "jax"
_ADDRESS = re.compile(r"^(?:(?P<proto>[a-z]+)://)?(?P<host>[^:/\s]+|\[[0-9a-fA-F:]+\]):(?P<port>\d+)$")


@dataclasses.dataclass(frozen=True)
class Task:
    """One photo of a batch, as the engine sees it.

    - `name`: the photo's name (its report folder's).
    - `folder`: the report folder; the photo is finished when it holds a fit result.
    - `payload`: what the work function needs to fit it (picklable).
    """

    name: str
    folder: Path
    payload: Any


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What became of one photo.

    - `name`: the photo's name.
    - `status`: ``"ok"``, ``"not converged"`` or ``"poor fit"`` (a report was written,
      see :func:`invglare.fit.batch_table.status_of`), or ``"failed"`` (no report:
      unreadable, refused, or the fit raised).
    - `reason`: why, for anything but ``"ok"`` (the solver's message, the error).
    - `worker`: the worker that fitted it (its address), or ``""``.
    """

    name: str
    status: str
    reason: str = ""
    worker: str = ""

    @property
    def failed(self) -> bool:
        return self.status != "ok"


class JaxWorkerSetup(WorkerPlugin):
    """A Dask worker plugin run once on every worker (also on those a nanny restarts).

    It points JAX's persistent compilation cache at `cache_dir` (programs compiled by one
    worker or run are loaded, not compiled, by the next, the solves among them: a batch's
    solves keep their loss history inside the program and hold no host callback, which JAX
    would not persist) and keeps XLA's freed buffers mapped. With
    `pin` (a LocalCluster's workers, named 0, 1, ...), it pins worker ``i`` to core
    ``i mod cores`` before JAX starts (:func:`pin_to_core`).
    """

    name = "invglare-jax-setup"
    idempotent = True

    def __init__(self, cache_dir: str | None, pin: bool = False):
        self.cache_dir = cache_dir
        self.pin = pin

    def setup(self, worker: Any = None) -> None:
        import jax

        from invglare._core.allocator import retain_freed_memory

        if self.pin and worker is not None and isinstance(worker.name, int):
            pin_to_core(worker.name)
        retain_freed_memory()
        if self.cache_dir:
            jax.config.update("jax_compilation_cache_dir", self.cache_dir)
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)



def pin_to_core(index: int) -> int | None:
    """Pin every thread of this process to one of the cores it may run on (the
    ``index``-th, cyclically), so that threads it starts later stay there too; return
    that core (None off Linux, where nothing is pinned).

    Why: XLA's CPU runtime runs independent operations of a program on a thread pool of
    its own, which the ``XLA_FLAGS`` of :func:`worker_env` do not shrink. An unpinned
    worker's fit of a population photo kept 1.5 cores busy (measured, 2-core machine), so
    two workers on two cores fought over them; pinned, it keeps one. Call it before
    JAX's backend starts, whose threads then start on that core too.
    """
    if not hasattr(os, "sched_setaffinity"):
        return None
    cores = sorted(os.sched_getaffinity(0))
    core = cores[index % len(cores)]
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that has just ended
            os.sched_setaffinity(int(tid), {core})
    return core


def check_address(address: str) -> str:
    """`address` if it looks like a scheduler's (``tcp://HOST:PORT`` or ``HOST:PORT``)."""
    if not _ADDRESS.match(address.strip()):
        raise ConfigError(
            f"--scheduler {address!r} is not a scheduler address; expected tcp://HOST:PORT "
            "(what `dask scheduler` prints as 'Scheduler at:')"
        )
    return address.strip()


def worker_env() -> dict[str, str]:
    """Environment of a LocalCluster's worker processes: XLA on one thread each."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "intra_op_parallelism_threads" not in flags:
        flags = f"{flags} {SINGLE_THREAD_XLA}".strip()
    return {"XLA_FLAGS": flags, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None,
    n_workers: int | None = None,
    *,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    connect_timeout_s: float = CONNECT_TIMEOUT_S,
    pin_cores: bool = True,
) -> Iterator[Any]:
    """A Dask client: of a new ``LocalCluster`` (closed on exit), or of `scheduler`.

    **Arguments:**

    - `scheduler`: address of a running scheduler (``tcp://HOST:PORT``), or None for a
      ``LocalCluster`` of `n_workers` processes (default: one per core), one thread each.
    - `cache_dir`: JAX's persistent compilation cache on the workers (None: none).
    - `connect_timeout_s`: how long to wait for `scheduler` to answer, and then for it to
      have a worker.
    - `pin_cores`: pin each LocalCluster worker to a core of its own (cyclically when
      there are more workers than cores; Linux only, see :func:`pin_to_core`).

    **Raises:** :class:`~invglare.errors.ConfigError` for a malformed address, a scheduler
    that does not answer within `connect_timeout_s`, one without workers, or fewer than
    one worker asked for.
    """
    import dask
    from distributed import Client, LocalCluster

    # The scheduler and nannies of a LocalCluster run in this process: their routine
    # messages (workers starting, closing, being killed at exit) are not the user's news.
    logging.getLogger("distributed").setLevel(logging.ERROR)
    cache = None if cache_dir is None else str(cache_dir)
    if scheduler is not None:
        address = check_address(scheduler)
        try:
            client = Client(address, timeout=connect_timeout_s)
        except (OSError, TimeoutError) as err:
            raise ConfigError(
                f"cannot reach a Dask scheduler at {address} within {connect_timeout_s:g} s "
                f"({type(err).__name__}: {err}); start one with `dask scheduler` and workers "
                f"with `dask worker {address} --nthreads 1`, or leave out --scheduler for a "
                "local cluster"
            ) from None
        try:
            try:
                client.wait_for_workers(1, timeout=connect_timeout_s)
            except TimeoutError:
                raise ConfigError(
                    f"the Dask scheduler at {address} has no worker after "
                    f"{connect_timeout_s:g} s; start some with `dask worker {address} "
                    "--nthreads 1`"
                ) from None
            # A cluster started elsewhere places its workers itself: nothing pinned.
            client.register_plugin(JaxWorkerSetup(cache))
            yield client
        finally:
            client.close()
        return
    n = (os.cpu_count() or 1) if n_workers is None else int(n_workers)
    if n < 1:
        raise ConfigError(f"--workers must be >= 1, got {n}")
    with dask.config.set({"distributed.worker.multiprocessing-method": "spawn"}):
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",  # any free port: no clash with a running cluster
            env=worker_env(),
            silence_logs=logging.ERROR,
        )
    try:
        client = Client(cluster)
        try:
            client.register_plugin(JaxWorkerSetup(cache, pin=pin_cores))
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def finished(folder: Path) -> FitResult | None:
    """The fit result in a photo's report folder, or None if it has none (or a broken one).

    Reports are written as whole folders, so ``params.json`` is there only when the
    report is complete.
    """
    params = Path(folder) / "params.json"
    if not params.is_file():
        return None
    try:
        return FitResult.from_json(params)
    except InputDataError:
        return None


def recover_unfinished(folders: Sequence[Path]) -> None:
    """Complete or remove what a killed run left beside each photo's report folder (a
    half-installed report is completed, a half-written one removed): taking a folder's
    lock does that (:func:`invglare.files.atomic.folder_lock`, ``recover_folder``).

    **Raises:** :class:`~invglare.errors.FolderBusyError` if another run writes one of them.
    """
    from invglare.files.atomic import folder_lock

    for folder in folders:
        if Path(folder).parent.is_dir():
            with folder_lock(folder, option="the photo's report folder"):
                pass


def run_tasks(
    client: Any,
    groups: Sequence[Sequence[Task]],
    work: Callable[[list[Any]], list[dict[str, str]]],
    *,
    progress: bool = True,
    skipped: int = 0,
) -> list[Outcome]:
    """Run `work` on every group of tasks on the cluster; **returns** each photo's outcome.

    `work(payloads)` runs on a worker and returns one ``{"status", "reason"}`` per payload
    (it catches a photo's own errors); an exception escaping it, or a task whose workers
    kept dying (Dask's ``KilledWorker``), fails the group's photos with that reason. The
    progress bar counts photos; `skipped` of them were done before this run.
    """
    from distributed import as_completed
    from tqdm import tqdm

    total = sum(len(g) for g in groups)
    token = uuid.uuid4().hex[:8]
    futures = {}
    for group in groups:
        key = f"invglare-fit-{group[0].name}-{token}"
        future = client.submit(_run_group, work, [t.payload for t in group], key=key, pure=False)
        futures[future] = group
    outcomes: list[Outcome] = []
    bar = tqdm(total=total + skipped, initial=skipped, desc="fit-batch", unit="photo",
               disable=not progress)  # fmt: skip
    try:
        for future in as_completed(futures):
            group = futures.pop(future)
            try:
                results, worker = future.result()
                got = [
                    Outcome(t.name, r["status"], r.get("reason", ""), worker)
                    for t, r in zip(group, results, strict=True)
                ]
            except Exception as err:  # the task itself failed: every photo in it did
                reason = _task_failure(err)
                got = [Outcome(t.name, "failed", reason) for t in group]
            for o in got:
                if o.failed:
                    log.warning("%s: %s: %s", o.name, o.status, o.reason)
            outcomes += got
            bar.update(len(group))
            bar.set_postfix_str(f"{sum(o.failed for o in outcomes)} failed", refresh=False)
    finally:
        bar.close()
        for future in futures:  # interrupted: nothing left running on the cluster
            future.cancel()
    return outcomes


def _run_group(work: Callable, payloads: list[Any]) -> tuple[list[dict[str, str]], str]:
    """On a worker: `work(payloads)` and the worker's address."""
    try:
        from distributed import get_worker

        address = get_worker().address
    except ValueError:  # not on a worker (a synchronous scheduler)
        address = ""
    return work(payloads), address


def _task_failure(err: BaseException) -> str:
    name = type(err).__name__
    if name == "KilledWorker":
        return (
            "the workers fitting it died repeatedly (out of memory or a crash); see the "
            f"workers' logs ({err})"
        )
    return f"{name}: {err}"

