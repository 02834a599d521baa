"""The one way the studies run many independent tasks: in order, in this process or a pool.

Every sweep (evaluation episodes, Pendulum-v1 seeds) is a list of small, picklable task inputs, a
function that runs one task in a worker, and an initializer that builds the worker's heavy state
once (env, controllers — their compiled code comes from the on-disk cache). :func:`run_tasks`
runs them serially or in spawned processes with one progress bar, and returns the results in the
order of the tasks, whichever worker finished first.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any, Callable, Sequence


def run_tasks(function: Callable[..., Any], tasks: Sequence[tuple[Any, ...]], initializer: Callable[..., None],
              initargs: tuple[Any, ...] = (), workers: int = 1, progress: bool = True,
              description: str = "tasks") -> list[Any]:
    """``[function(*task) for task in tasks]`` after ``initializer(*initargs)`` in each worker.

    Args:
        function: module-level (picklable) function of one task's arguments.
        tasks: each task's positional arguments.
        initializer: builds the worker state ``function`` reads; also run here when serial.
        workers: processes; ``1`` runs in this process.
        progress: one tqdm bar over all tasks.

    Raises:
        ValueError: ``workers < 1``. A task's exception propagates (the pool is shut down).
    """
    from tqdm.auto import tqdm

    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    results: list[Any] = [None] * len(tasks)
    with tqdm(total=len(tasks), desc=description, disable=not progress) as bar:
        if workers == 1 or len(tasks) <= 1:
            initializer(*initargs)
            for i, task in enumerate(tasks):
                results[i] = function(*task)
                bar.update()
            return results
        # spawn, not fork: CasADi's compiled libraries and MuJoCo's state are not fork-safe.
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                                 initializer=initializer, initargs=initargs) as pool:
            futures = {pool.submit(function, *task): i for i, task in enumerate(tasks)}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
    return results

