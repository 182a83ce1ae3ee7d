"""Dask clusters for work beyond one device: a local cluster of CPU processes or of one process per
GPU (each with its own CUDA_VISIBLE_DEVICES), the cluster a run uses by default, and a map over a
cluster that retries a failed item once and fails the run in one line when it fails twice. Dask
moves only our own arrays and settings between our own workers; no model or checkpoint is ever
loaded through it."""

from __future__ import annotations

from ...errors import WarpgaussError


def map_on_cluster(client, fn, items: list, keys: list[str], what: str, tail: str = "", after=None) -> list:
    """``fn`` over ``items`` on a Dask cluster, results in item order. An item that fails is
    retried once; one that fails twice cancels the rest and fails the run in one line (``what``
    names the item, ``tail`` ends the line). ``after(done, index, result)`` as each comes back."""
    from distributed import as_completed

    futures = client.map(fn, items, retries=1, pure=False, key=keys)
    index = {f.key: i for i, f in enumerate(futures)}
    out: list = [None] * len(items)
    done = 0
    try:
        for fut in as_completed(futures):
            i = index[fut.key]
            out[i] = fut.result()
            done += 1
            if after is not None:
                after(done, i, out[i])
    except Exception as e:  # an item that failed twice (its retry included)
        for fut in futures:
            fut.cancel()
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise WarpgaussError(f"{what} failed on the Dask cluster twice: {type(e).__name__}: {first}{tail}") from None
    return out


def is_local(client) -> bool:
    """Whether every worker of ``client``'s cluster can read a file this process writes (a local
    cluster's workers, on this machine): asked of the workers themselves, with a file of a random
    token in a temporary folder (a host name or address says too little: a machine may name itself
    differently to its workers)."""
    import secrets

    from ...readers.lazy import shared_folder

    with shared_folder() as folder:
        token = secrets.token_hex(16)
        path = f"{folder}/probe"
        with open(path, "w") as fh:
            fh.write(token)
        try:
            seen = client.run(reads_token, path, token)
        except Exception:  # a worker that cannot answer is not assumed to share our files
            return False
    return bool(seen) and all(seen.values())


def share_arrays(client, arrays, stack) -> tuple[list | None, str | None]:
    """``arrays`` (3D, or None) for ``client``'s workers: written once to temporary files that they
    read (:func:`warpgauss.readers.lazy.shared`, kept while ``stack``, a :class:`contextlib.ExitStack`,
    is open) where they run on this machine (:func:`is_local`); else None, and the arrays travel
    in the task graph. The second value says why a local cluster got none (no room in $TMPDIR)."""
    from ...readers.lazy import shared

    if not is_local(client):
        return None, None
    try:
        return stack.enter_context(shared(arrays)), None
    except OSError as e:
        return None, f"no shared copy: {e.strerror or e}"


def reads_token(path: str, token: str) -> bool:
    """Whether this process (a Dask worker, asked by :func:`is_local`) reads ``token`` at ``path``."""
    try:
        with open(path) as fh:
            return fh.read() == token
    except OSError:
        return False


def local_client(workers: int):
    """A local Dask cluster of ``workers`` single-threaded processes (Warp's CPU device runs a
    kernel on one thread), and its client."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    return Client(cluster)


def gpu_ids(count: int) -> list[str]:
    """The first ``count`` GPUs this process may use, as CUDA_VISIBLE_DEVICES entries (that
    variable's own list where it is set, else 0, 1, ...)."""
    import os

    visible = [g.strip() for g in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if g.strip()]
    ids = visible if visible else [str(i) for i in range(count)]
    if len(ids) < count:
        raise WarpgaussError(f"{count} GPU workers asked for, but only {len(ids)} GPUs are visible ({','.join(ids)})")
    return ids[:count]


def gpu_client(gpus: int, ids: list[str] | None = None):
    """A local Dask cluster of one single-threaded worker process per GPU, and its client.

    Each worker is started with CUDA_VISIBLE_DEVICES naming its own GPU, so in it "cuda:0" is that
    GPU and a brick task (device None: CUDA when present) runs there; what dask-cuda's
    LocalCUDACluster does for this, without its other machinery (UCX, RMM) or the dependency.
    Only Dask's own transports are used. ``ids``: the GPUs (default: :func:`gpu_ids`).

    Each worker may use an equal share of the host's memory: Dask's default, the host's memory
    times threads over cores, gave a single-threaded worker 7.9 GiB of 256 GiB on 32 cores, and
    its nanny restarted the one GPU worker of a 2048^3 out-of-core encode until the brick failed."""
    from distributed import Client, Nanny, Scheduler, SpecCluster
    from distributed.system import MEMORY_LIMIT

    ids = gpu_ids(gpus) if ids is None else [str(i) for i in ids]
    share = int(MEMORY_LIMIT // max(1, len(ids)))
    workers = {
        f"gpu-{g}": {
            "cls": Nanny,
            "options": {"nthreads": 1, "env": {"CUDA_VISIBLE_DEVICES": g}, "name": f"gpu-{g}", "memory_limit": share},
        }
        for g in ids
    }
    cluster = SpecCluster(workers=workers, scheduler={"cls": Scheduler, "options": {"dashboard_address": None}}, name="warpgauss-gpus")
    return Client(cluster)


def default_client(workers: int | None, scheduler: str | None, device: str | None):
    """The cluster a bricked encode runs on, and a note of why.

    ``scheduler``: connect to that running cluster. ``workers`` 0: this process. Otherwise a local
    cluster: one worker per GPU (:func:`gpu_client`; ``workers`` of them at most) where several
    GPUs exist; this process on a single GPU (the bricks share it anyway); on the CPU ``workers``
    processes (default: up to 4, one per core).
    """
    import os

    if scheduler is not None:
        from distributed import Client

        return Client(scheduler), f"the cluster at {scheduler}"
    if workers == 0:
        return None, "this process (--workers 0)"
    from ...core.warp import resolve_device, warp

    dev = resolve_device(device)
    if dev.startswith("cuda"):
        gpus = warp().get_cuda_device_count()
        if gpus > 1:
            k = min(workers or gpus, gpus)
            return gpu_client(k), f"a local cluster of {k} GPU workers (one GPU each)"
        return None, "this process (one GPU: the bricks share it)"
    k = workers or max(1, min(4, os.cpu_count() or 1))
    return local_client(k), f"a local cluster of {k} CPU processes"
