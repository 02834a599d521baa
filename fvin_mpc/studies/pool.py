"""The one way the studies run many independent tasks: in order, here, in a process pool or on Ray.

Every sweep (evaluation episodes, Pendulum-v1 seeds, bench rows, training runs) is a list of
small, picklable task inputs, a function that runs one task in a worker, and an initializer that
builds the worker's heavy state once (env, controllers — their compiled code comes from the
on-disk cache —, training data). :func:`run_tasks` runs them with one progress bar and returns
the results in the order of the tasks, whichever worker finished first:

* ``backend="process"`` (default, nothing to install): serially in this process for
  ``workers=1``, else in ``workers`` spawned processes;
* ``backend="ray"``: one Ray actor per worker (one CPU each) runs the initializer once, then
  takes tasks as it frees up. ``address`` (or the standard ``RAY_ADDRESS``) connects to an
  existing cluster; without either a local cluster of ``workers`` CPUs is started for the call
  and shut down after it. A session this process already opened (``ray.init``) is reused.
  Ray is an optional extra: ``pip install -e ".[ray]"``.

A task that raises does not stop the others: every task runs, then :class:`TasksFailed` is
raised with the finished results (``None`` where a task failed) and, per failure, the task's
inputs and its error. All backends behave the same way.
"""

from __future__ import annotations

import contextlib
import os
import sys
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any, Callable, Iterator, Literal, Sequence

Backend = Literal["process", "ray"]
BACKENDS: tuple[str, ...] = ("process", "ray")
#: Tasks kept queued per Ray actor beyond the one it runs (hides the round trip; small, so a
#: slow actor does not hold back work a free one could take).
RAY_QUEUE_PER_ACTOR = 1


@dataclass(frozen=True)
class TaskFailure:
    """One task that raised: its position, inputs and error (type, message, worker traceback)."""

    index: int
    inputs: tuple[Any, ...]
    error: str
    traceback: str = ""

    def describe(self, width: int = 200) -> str:
        inputs = repr(self.inputs)
        inputs = inputs if len(inputs) <= width else inputs[: width - 1] + "…"
        return f"task {self.index} {inputs}: {self.error}"


class TasksFailed(RuntimeError):
    """Some tasks raised. ``results`` holds every finished result in task order (``None`` at the
    failed positions), ``failures`` the failed tasks with their inputs; the message lists them."""

    def __init__(self, results: list[Any], failures: list[TaskFailure], description: str = "tasks") -> None:
        self.results = results
        self.failures = failures
        lines = [f"{len(failures)} of {len(results)} {description} failed "
                 f"({len(results) - len(failures)} finished and kept):"]
        lines += [f"  {failure.describe()}" for failure in failures[:20]]
        if len(failures) > 20:
            lines.append(f"  … and {len(failures) - 20} more")
        super().__init__("\n".join(lines))


def run_tasks(function: Callable[..., Any], tasks: Sequence[tuple[Any, ...]],
              initializer: Callable[..., None] | None = None, initargs: tuple[Any, ...] = (), workers: int = 1,
              progress: bool = True, description: str = "tasks", backend: Backend = "process",
              address: str | None = None) -> list[Any]:
    """``[function(*task) for task in tasks]`` after ``initializer(*initargs)`` in each worker.

    Args:
        function: module-level (importable) function of one task's arguments.
        tasks: each task's positional arguments: small values (names, seeds, settings).
        initializer: builds the worker state ``function`` reads (run once per worker; here when
            serial); ``None``: nothing to build.
        initargs: its arguments, sent once per worker (Ray: put in the object store once).
        workers: processes or Ray actors; ``1`` with the process backend runs in this process.
        progress: one tqdm bar over all tasks, on this (the driver's) side.
        description: the bar's label and the failure message's noun.
        backend: ``"process"`` or ``"ray"`` (module docstring).
        address: Ray cluster address (``"auto"``, ``"ray://head:10001"``, ``"10.0.0.1:6379"``);
            ``None``: ``RAY_ADDRESS`` if set, else a local cluster for this call.

    Returns:
        The results, in the order of ``tasks``.

    Raises:
        ValueError: ``workers < 1`` or an unknown backend.
        TasksFailed: after every task ran, if any raised (finished results kept on it).
        ImportError: ``backend="ray"`` without Ray installed.
    """
    from tqdm.auto import tqdm

    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose from {', '.join(BACKENDS)}")
    tasks = [tuple(task) for task in tasks]
    results: list[Any] = [None] * len(tasks)
    failures: list[TaskFailure] = []
    initializer = initializer or _nothing
    with tqdm(total=len(tasks), desc=description, disable=not progress) as bar:
        if backend == "ray":
            _run_ray(function, tasks, initializer, initargs, workers, address, results, failures, bar)
        elif workers == 1 or len(tasks) <= 1:
            initializer(*initargs)
            for i, task in enumerate(tasks):
                try:
                    results[i] = function(*task)
                except Exception as error:  # noqa: BLE001 — reported with the task's inputs below
                    failures.append(_failure(i, task, error))
                bar.update()
        else:
            _run_processes(function, tasks, initializer, initargs, workers, results, failures, bar)
    if failures:
        failures.sort(key=lambda failure: failure.index)
        raise TasksFailed(results, failures, description)
    return results


def _nothing(*_: Any) -> None:
    """The initializer of tasks that need no worker state."""


def _failure(index: int, task: tuple[Any, ...], error: BaseException) -> TaskFailure:
    text = "".join(traceback.format_exception(type(error), error, error.__traceback__))
    return TaskFailure(index, task, f"{type(error).__name__}: {error}", text)


# ---------------------------------------------------------------------- process pool
def _run_processes(function: Callable[..., Any], tasks: list[tuple[Any, ...]], initializer: Callable[..., None],
                   initargs: tuple[Any, ...], workers: int, results: list[Any], failures: list[TaskFailure],
                   bar: Any) -> None:
    # spawn, not fork: CasADi's compiled libraries and MuJoCo's state are not fork-safe.
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                             initializer=initializer, initargs=initargs) as pool:
        futures = {pool.submit(function, *task): i for i, task in enumerate(tasks)}
        for future in as_completed(futures):
            i = futures[future]
            try:
                results[i] = future.result()
            except Exception as error:  # noqa: BLE001 — incl. a worker that died (BrokenProcessPool)
                failures.append(_failure(i, tasks[i], error))
            bar.update()


# ---------------------------------------------------------------------- Ray
def ray_environment() -> dict[str, str]:
    """Environment for a Ray session started here: no usage-stats upload (the machine may be
    offline; ``ray.init`` must never wait on the network)."""
    return {"RAY_USAGE_STATS_ENABLED": "0", "RAY_DISABLE_DOCKER_CPU_WARNING": "1"}


@contextlib.contextmanager
def ray_session(address: str | None = None, num_cpus: int | None = None) -> Iterator[Any]:
    """A Ray session for the block; yields the ``ray`` module.

    Reuses a session this process already has. Otherwise connects to ``address`` (or
    ``RAY_ADDRESS``) or, without either, starts a local cluster of ``num_cpus`` CPUs (no
    dashboard, usage stats off); what it opened it shuts down at the end of the block.
    """
    for key, value in ray_environment().items():
        os.environ.setdefault(key, value)
    try:
        import ray
    except ImportError:
        raise ImportError('the Ray backend needs Ray: pip install -e ".[ray]"') from None
    if ray.is_initialized():
        yield ray
        return
    if address or os.environ.get("RAY_ADDRESS"):
        ray.init(address=address, logging_level="WARNING")
    else:
        ray.init(num_cpus=num_cpus, include_dashboard=False, logging_level="WARNING")
    try:
        yield ray
    finally:
        ray.shutdown()


class _Worker:
    """One Ray actor: the initializer's state built once, then tasks one at a time."""

    def __init__(self, function: Callable[..., Any], initializer: Callable[..., None],
                 initargs: tuple[Any, ...]) -> None:
        self.function = function
        initializer(*initargs)

    def run(self, *task: Any) -> Any:
        return self.function(*task)


def _run_ray(function: Callable[..., Any], tasks: list[tuple[Any, ...]], initializer: Callable[..., None],
             initargs: tuple[Any, ...], workers: int, address: str | None, results: list[Any],
             failures: list[TaskFailure], bar: Any) -> None:
    with ray_session(address, num_cpus=workers) as ray:
        cpus = int(ray.cluster_resources().get("CPU", 0))
        if 0 < cpus < workers:
            # An actor asks for one CPU: more actors than the cluster has CPUs would wait forever.
            print(f"ray: {workers} workers asked, the cluster has {cpus} CPUs: using {cpus}", file=sys.stderr)
            workers = cpus
        workers = max(1, min(workers, len(tasks)))
        if not tasks:
            return
        actor_class = ray.remote(num_cpus=1, max_restarts=0)(_Worker)
        # Sent once, fetched by each actor (a top-level reference argument arrives as its value).
        shared = ray.put(initargs)
        actors = [actor_class.remote(function, initializer, shared) for _ in range(workers)]
        pending = list(range(len(tasks)))[::-1]  # a stack: pop() gives the lowest index first
        running: dict[Any, tuple[int, Any]] = {}  # object ref → (task index, actor)
        load = {actor: 0 for actor in actors}

        def submit(actor: Any) -> None:
            while pending and load[actor] <= RAY_QUEUE_PER_ACTOR:
                i = pending.pop()
                running[actor.run.remote(*tasks[i])] = (i, actor)
                load[actor] += 1

        for actor in actors:
            submit(actor)
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            i, actor = running.pop(done[0])
            load[actor] -= 1
            try:
                results[i] = ray.get(done[0])
            except ray.exceptions.RayTaskError as error:
                failures.append(TaskFailure(i, tasks[i], f"{_cause_name(error)}: {_cause_message(error)}",
                                            str(error)))
            except ray.exceptions.RayError as error:  # the actor (or its node) died, or its initializer raised
                failures.append(TaskFailure(i, tasks[i], f"{type(error).__name__}: {_first_line(error)}", str(error)))
                if isinstance(error, ray.exceptions.RayActorError):
                    load.pop(actor, None)
            bar.update()
            if actor in load:
                submit(actor)
            elif not load:  # no actor left: the rest cannot run
                for j in sorted(pending):
                    failures.append(TaskFailure(j, tasks[j], "RuntimeError: no Ray worker left to run it"))
                    bar.update()
                pending.clear()
        for actor in actors:
            ray.kill(actor)


def _cause_name(error: Any) -> str:
    cause = getattr(error, "cause", None)
    return type(cause).__name__ if cause is not None else getattr(error, "function_name", type(error).__name__)


def _cause_message(error: Any) -> str:
    cause = getattr(error, "cause", None)
    return str(cause) if cause is not None else _first_line(error)


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__

