"""One Dask client for the dataset builder and the evaluation: the caller's, one connected to a scheduler, or one
of a new local cluster (one single-threaded worker process per ``workers``), closed on exit when it is made here.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from polinfra.errors import ConfigError, OutputError


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2, client=None, *, what: str = "a Dask run") -> Iterator:
    """A ``distributed.Client``: ``client`` itself, one connected to ``scheduler``, or one of a new LocalCluster.

    Args:
        scheduler: the scheduler's address (``tcp://HOST:8786``), or None for a local cluster.
        workers: worker processes of the local cluster (>= 1).
        client: an existing client, used as is and not closed.
        what: names the job in the error when the ``distributed`` package is missing.
    """
    if client is not None:
        yield client
        return
    try:
        import distributed
    except ImportError:
        raise ConfigError(f"{what} needs the 'distributed' package (pip install 'dask[distributed]')") from None
    if workers < 1:
        raise ConfigError(f"--workers {workers}: a local Dask cluster needs >= 1 worker")
    cluster = None
    if scheduler:
        try:
            c = distributed.Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise OutputError(f"cannot connect to the Dask scheduler {scheduler!r} ({exc}); check the address (tcp://HOST:8786)") from None
    else:
        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
        c = distributed.Client(cluster)
    try:
        yield c
    finally:
        with contextlib.suppress(Exception):
            c.close()
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()
