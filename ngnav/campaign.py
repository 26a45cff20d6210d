"""Campaigns of independent runs on dask.distributed: here, on a local cluster, or on yours.

A campaign is ``fn(i)`` for each run index ``i``. Each run draws its randomness from its
own index (the scenarios' ``default_rng([seed, i])``), so its result is the same wherever
it executes. Runs are submitted as futures and handed to ``on_result`` as they finish, in
whatever order (no barrier between batches); a run that raises is reported with its index
and error and the others go on.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class RunFailure:
    """A run that raised instead of returning: its index and the error, one line."""

    run: int
    error: str


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def run_campaign(
    fn: Callable[[int], Any],
    runs: Iterable[int],
    on_result: Callable[[int, Any], None],
    *,
    workers: int = 2,
    scheduler: str | None = None,
    progress: bool = False,
    desc: str = "runs",
) -> list[RunFailure]:
    """Run ``fn(i)`` for every index in ``runs``; give each result to ``on_result(i, value)``.

    Parameters
    ----------
    fn : callable
        A picklable function of the run index (a module-level function, or a
        ``functools.partial`` of one) for the workers' processes.
    runs : iterable of int
        The run indices.
    on_result : callable
        Called in this process with each run's index and result as it arrives.
    workers : int
        With no ``scheduler``: 1 runs here, one run after another; N > 1 starts a local
        dask.distributed cluster of N single-threaded worker processes for the campaign.
    scheduler : str, optional
        Address of a running dask scheduler (``tcp://HOST:8786``): the runs go to its
        workers, which must have ngnav installed; ``workers`` is then ignored.
    progress : bool
        A tqdm bar on stderr, advanced as runs finish.

    Returns
    -------
    list of RunFailure
        The runs that raised, in run order.
    """
    from tqdm import tqdm

    indices = [int(i) for i in runs]
    failures: list[RunFailure] = []
    bar = tqdm(total=len(indices), desc=desc, disable=not progress, unit="run")
    try:
        if scheduler is None and workers <= 1:
            for i in indices:
                try:
                    value = fn(i)
                except Exception as exc:  # a run's failure is reported; the others go on
                    failures.append(RunFailure(i, _one_line(exc)))
                else:
                    on_result(i, value)
                bar.update(1)
            return failures
        _distributed(fn, indices, on_result, workers, scheduler, failures, bar)
    finally:
        bar.close()
    return sorted(failures, key=lambda f: f.run)


def _distributed(fn, indices, on_result, workers, scheduler, failures, bar) -> None:
    from distributed import Client, LocalCluster, as_completed

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except OSError as exc:
            raise ValueError(f"no dask scheduler at {scheduler}: {_one_line(exc)}") from None
        cluster = None
    else:
        # one thread per process: the filter is Python-bound, the GIL would serialise threads;
        # the scheduler's HTTP server on a free port (its default, 8787, is taken by any other
        # cluster on the machine, and dask then warns or fails)
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0"
        )
        client = Client(cluster)
    try:
        futures = {client.submit(fn, i, pure=False): i for i in indices}
        for fut in as_completed(futures):
            i = futures[fut]
            if fut.status == "error":
                failures.append(RunFailure(i, _one_line(fut.exception())))
            else:
                on_result(i, fut.result())
            fut.release()
            bar.update(1)
    finally:
        # closed as it is: retiring the workers first (against a heartbeat race,
        # dask/distributed#7105) put dask's log lines on the user's terminal at every
        # campaign's end (tests/test_campaign.py)
        client.close()
        if cluster is not None:
            cluster.close()
