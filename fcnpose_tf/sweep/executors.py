"""Where sweep jobs run: in this process, in N local worker processes, or as Ray tasks.

All three run the same job function with the same arguments and honour the same dependency:
a fold's rate jobs start only after that fold's base job finished (a failed base skips them).
Every job writes its own record when it is done, so the executors only schedule and report:

    LocalExecutor(workers=1)   sequential, in this process, fold by fold
    LocalExecutor(workers=N)   N spawned processes (concurrent.futures), each limited to
                               `threads` TensorFlow/OpenMP threads before TensorFlow starts
    RayExecutor(address=None)  a local Ray instance (num_cpus CPUs), or the cluster at `address`;
                               one task per job, `threads` CPUs each, rate tasks depending on
                               their fold's base task through its ObjectRef

Ctrl-C stops the sweep: running jobs are stopped (their work is lost, nothing else), finished
jobs keep their records, and rerunning continues. `ray` is imported only by RayExecutor.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import traceback
from abc import ABC, abstractmethod
from typing import Any, Callable, Iterator, Sequence, TypedDict

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import note_stop_signal
from fcnpose_tf.sweep.jobs import Job, JobEvent, JobRecord

JobFunction = Callable[[Any, Job], JobRecord]
"""run_job(config, job) -> record: module-level, picklable arguments."""
EventHandler = Callable[[JobEvent], None]

RAY_MISSING = "the ray executor needs Ray: pip install 'fcnpose-tf[ray]'"


def thread_env(threads: int) -> dict[str, str]:
    """Environment that caps a fresh process's TensorFlow/OpenMP/BLAS threads (read when TF starts)."""
    n = str(int(threads))
    return {"TF_NUM_INTRAOP_THREADS": n, "TF_NUM_INTEROP_THREADS": "1", "OMP_NUM_THREADS": n,
            "OPENBLAS_NUM_THREADS": n, "MKL_NUM_THREADS": n, "TF_CPP_MIN_LOG_LEVEL": "3"}


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """Turn SIGINT and SIGTERM into KeyboardInterrupt while jobs run; the event records that one came.

    Installed explicitly because a sweep started in the background (`nohup ... &`) inherits an
    ignored SIGINT, and SIGTERM would otherwise end the driver without stopping its workers. The
    event also tells a KeyboardInterrupt that a job turned into another exception (fit() raises
    UserError on Ctrl-C) from a real job failure.
    """
    event = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield event
        return

    def handler(signum, frame):
        event.set()
        note_stop_signal(signum)  # the CLI's one line and exit status (130 or 143) name the signal
        raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield event
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def _error_text(exc: BaseException) -> str:
    if isinstance(exc, UserError):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


class ExecutorInfo(TypedDict, total=False):
    """An executor's settings as a run entry of sweep.json records them (`Executor.describe`)."""

    executor: str
    """"local" or "ray"."""
    workers: int
    """The local executor's processes."""
    address: str | None
    """The Ray cluster joined (None: a local Ray instance)."""
    num_cpus: int | None
    """CPUs of a local Ray instance (None: all cores)."""
    threads_per_job: int
    cluster: dict[str, float | int]
    """The Ray cluster once joined: its "cpus" and "nodes"."""


class Executor(ABC):
    """Runs jobs, respecting base-before-rates per fold, and reports each as a JobEvent."""

    name = "executor"

    @abstractmethod
    def describe(self) -> ExecutorInfo:
        """JSON-ready settings (recorded in results.json)."""

    @abstractmethod
    def run(self, fn: JobFunction, config: Any, jobs: Sequence[Job], finished: set[str],
            on_event: EventHandler) -> None:
        """Run `jobs` (none of them finished); `finished` holds names of jobs already done.

        Raises KeyboardInterrupt after stopping the running jobs when interrupted.
        """


def _ready(job: Job, finished: set[str]) -> bool:
    return job.is_base or job.base().name in finished


class LocalExecutor(Executor):
    """Sequential in this process (workers=1), or `workers` spawned processes."""

    name = "local"

    def __init__(self, workers: int = 1, threads: int = 1):
        if workers < 1:
            raise UserError(f"--workers must be at least 1, got {workers}")
        self.workers = int(workers)
        self.threads = int(threads)

    def describe(self) -> ExecutorInfo:
        return {"executor": self.name, "workers": self.workers, "threads_per_job": self.threads}

    def run(self, fn: JobFunction, config: Any, jobs: Sequence[Job], finished: set[str],
            on_event: EventHandler) -> None:
        with stop_on_signals() as interrupted:
            if self.workers == 1:
                self._run_here(fn, config, jobs, set(finished), on_event, interrupted)
            else:
                self._run_pool(fn, config, jobs, set(finished), on_event)

    # -- sequential ------------------------------------------------------------------------
    def _run_here(self, fn: JobFunction, config: Any, jobs: Sequence[Job], finished: set[str],
                  on_event: EventHandler, interrupted: threading.Event) -> None:
        for job in sorted(jobs, key=lambda j: (j.fold, not j.is_base, j.rate or 0.0)):
            if not _ready(job, finished):
                on_event(JobEvent("skipped", job, error=f"fold {job.fold}'s base model failed"))
                continue
            on_event(JobEvent("started", job))
            try:
                record = fn(config, job)
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # noqa: BLE001 - one failed job must not end a long sweep
                if interrupted.is_set():  # fit() turned the Ctrl-C into a UserError
                    raise KeyboardInterrupt from None
                on_event(JobEvent("failed", job, error=_error_text(exc),
                                  details={} if isinstance(exc, UserError) else {"traceback": traceback.format_exc()}))
                continue
            finished.add(job.name)
            on_event(JobEvent("done", job, record=record))

    # -- process pool ----------------------------------------------------------------------
    def _run_pool(self, fn: JobFunction, config: Any, jobs: Sequence[Job], finished: set[str],
                  on_event: EventHandler) -> None:
        import multiprocessing
        from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool

        waiting = sorted(jobs, key=lambda j: (not j.is_base, j.fold, j.rate or 0.0))  # bases first: unlock folds
        failed: set[str] = set()
        running: dict[Future, Job] = {}
        pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_init_worker, initargs=(self.threads,))
        try:
            while waiting or running:
                for job in list(waiting):
                    if not job.is_base and job.base().name in failed:
                        waiting.remove(job)
                        on_event(JobEvent("skipped", job, error=f"fold {job.fold}'s base model failed"))
                    elif len(running) < self.workers and _ready(job, finished):
                        waiting.remove(job)
                        running[pool.submit(fn, config, job)] = job  # never queue more than can run
                        on_event(JobEvent("started", job))
                if not running:
                    break
                done, _ = wait(list(running), return_when=FIRST_COMPLETED)
                for future in done:
                    job = running.pop(future)
                    try:
                        record = future.result()
                    except BrokenProcessPool:
                        failed.add(job.name)
                        for other in list(running.values()) + [job]:
                            on_event(JobEvent("failed", other, error="its worker process died (out of memory? "
                                                                     "killed? a script's code not under `if "
                                                                     "__name__ == \"__main__\":`?)"))
                        raise UserError("a sweep worker process died; the jobs still to run were not started; "
                                        "rerun to continue (fewer --workers needs less memory; from a Python script, "
                                        "put the sweep under `if __name__ == \"__main__\":`, which the worker "
                                        "processes start again)") from None
                    except Exception as exc:  # noqa: BLE001
                        failed.add(job.name)
                        on_event(JobEvent("failed", job, error=_error_text(exc),
                                          details={} if isinstance(exc, UserError) else {"traceback": "".join(
                                              traceback.format_exception(type(exc), exc, exc.__traceback__))}))
                    else:
                        finished.add(job.name)
                        on_event(JobEvent("done", job, record=record))
        except BaseException:
            for future in running:
                future.cancel()
            _terminate_workers(pool)
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        pool.shutdown(wait=True)


def _init_worker(threads: int) -> None:
    """Pool worker start-up: cap threads before TensorFlow is imported; leave Ctrl-C to the driver."""
    os.environ.update(thread_env(threads))
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _terminate_workers(pool: Any) -> None:
    """Stop a ProcessPoolExecutor's workers now (the running jobs are lost, finished ones are saved)."""
    for process in list(getattr(pool, "_processes", {}).values()):  # Python < 3.14 has no public API for this
        if process.is_alive():
            process.terminate()
    for process in list(getattr(pool, "_processes", {}).values()):
        process.join(timeout=10)


class RayExecutor(Executor):
    """Every job a Ray task: a local instance (`num_cpus` CPUs) or an existing cluster (`address`)."""

    name = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None, threads: int = 1):
        if address and num_cpus is not None:
            raise UserError("--num-cpus sizes a local Ray instance; a cluster at --address has its own CPUs")
        if num_cpus is not None and num_cpus < 1:
            raise UserError(f"--num-cpus must be at least 1, got {num_cpus}")
        if num_cpus is not None and threads > num_cpus:
            raise UserError(f"--threads {threads} is more than the Ray instance's --num-cpus {num_cpus}: "
                            "no task could ever be scheduled")
        self.address = address
        self.num_cpus = num_cpus
        self.threads = int(threads)
        self.cluster: dict[str, float | int] = {}

    def describe(self) -> ExecutorInfo:
        return {"executor": self.name, "address": self.address, "num_cpus": self.num_cpus,
                "threads_per_job": self.threads, **({"cluster": self.cluster} if self.cluster else {})}

    def _init(self, ray: Any) -> None:
        common = {"logging_level": "WARNING", "log_to_driver": True}
        try:
            if self.address:
                ray.init(address=self.address, **common)
            else:  # only records travel through the object store: keep it small
                ray.init(num_cpus=self.num_cpus or os.cpu_count(), object_store_memory=256 * 2**20,
                         include_dashboard=False, **common)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = f"the Ray cluster at {self.address}" if self.address else "a local Ray instance"
            raise UserError(f"cannot start or reach {where}: {exc}") from None
        resources = ray.cluster_resources()
        cpus = float(resources.get("CPU", 0))
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        self.cluster = {"cpus": cpus, "nodes": len(nodes)}
        if cpus < self.threads:
            ray.shutdown()
            raise UserError(f"the Ray cluster has {cpus:g} CPUs, fewer than --threads {self.threads} per task")

    def run(self, fn: JobFunction, config: Any, jobs: Sequence[Job], finished: set[str],
            on_event: EventHandler) -> None:
        try:
            import ray
        except ImportError:
            raise UserError(RAY_MISSING) from None
        with stop_on_signals():
            self._run_ray(ray, fn, config, jobs, finished, on_event)

    def _run_ray(self, ray: Any, fn: JobFunction, config: Any, jobs: Sequence[Job], finished: set[str],
                 on_event: EventHandler) -> None:
        from ray.exceptions import RayError, RayTaskError

        self._init(ray)
        remote = ray.remote(_ray_job).options(num_cpus=self.threads, max_retries=1,
                                              runtime_env={"env_vars": thread_env(self.threads)})
        refs: dict[Any, Job] = {}
        base_refs: dict[int, Any] = {}
        try:
            for job in sorted(jobs, key=lambda j: (not j.is_base, j.fold, j.rate or 0.0)):
                if job.is_base:
                    base_refs[job.fold] = ref = remote.remote(fn, config, job)
                elif job.fold in base_refs:  # the base runs too: wait for it through its result
                    ref = remote.remote(fn, config, job, base_refs[job.fold])
                else:
                    ref = remote.remote(fn, config, job)
                refs[ref] = job
                on_event(JobEvent("submitted", job))
            failed_bases: set[int] = set()
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                ref = ready[0]
                job = refs[ref]
                try:
                    record = ray.get(ref)
                except RayError as exc:
                    if not job.is_base and (job.fold in failed_bases or _failed(ray, base_refs.get(job.fold))):
                        on_event(JobEvent("skipped", job, error=f"fold {job.fold}'s base model failed"))
                        continue
                    if job.is_base:
                        failed_bases.add(job.fold)
                    cause = exc.cause if isinstance(exc, RayTaskError) and getattr(exc, "cause", None) else exc
                    on_event(JobEvent("failed", job, error=_error_text(cause),
                                      details={} if isinstance(cause, UserError) else {"traceback": str(exc)}))
                else:
                    finished.add(job.name)
                    on_event(JobEvent("done", job, record=record))
        except BaseException:
            for ref in refs:
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # noqa: BLE001 - already finished or gone
                    pass
            raise
        finally:
            ray.shutdown()


def _failed(ray: Any, ref: Any) -> bool:
    """Whether a finished Ray task raised (False while it runs or when there is none)."""
    if ref is None or not ray.wait([ref], timeout=0)[0]:
        return False
    try:
        ray.get(ref)
    except Exception:  # noqa: BLE001
        return True
    return False


def _ray_job(fn: JobFunction, config: Any, job: Job, *dependencies: Any) -> JobRecord:
    """A Ray task: run the job (thread caps come from the task's env; `dependencies` only order it)."""
    return fn(config, job)
