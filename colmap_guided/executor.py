"""Where pairs are matched: threads of this process (``local``, the default) or a Ray cluster
(``ray``).

``match.match_database`` drives both the same way (ordering, resume, database writes, releasing an
image once its last pair is matched): it ``put``s each image once, ``submit``s pairs, keeps at most
``capacity`` of them in flight and collects finished ones with ``wait`` (in completion order).

Ray (``pip install colmap_guided[ray]``): the driver puts each image's keypoints, descriptors and
backbone features in the object store once; one actor per cluster CPU holds a copy of the matcher
(the coarse network loads once per worker, from the driver's object, so workers need neither the
photos nor the weights file) and runs on the matcher's torch threads (one if it leaves them as they
are; Ray reuses its worker processes). Without an address (``--ray_address`` or ``RAY_ADDRESS``) a
private local instance is started and stopped — never a running cluster joined by accident. Clusters
started by ``ray start`` use token authentication by default: the driver needs the cluster's token
(``RAY_AUTH_TOKEN`` or ``~/.ray/auth_token``).
"""

from __future__ import annotations

import os
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

from .log import logger
from .matchers.base import ImageData, Matcher

EXECUTORS = ("local", "ray")


class LocalExecutor:
    """``matcher.pair_workers`` threads of this process (torch releases the GIL); two pairs per
    thread queued."""

    def __init__(self, matcher: Matcher, verification: dict | None = None):
        self.matcher, self.verification = matcher, verification or {}
        self.workers = max(1, int(matcher.pair_workers))
        self.capacity = 2 * self.workers
        self.pool = ThreadPoolExecutor(self.workers)
        self.futures: dict = {}

    def put(self, image: ImageData) -> ImageData:
        return image

    def submit(self, key, a: ImageData, b: ImageData) -> None:
        self.futures[self.pool.submit(self.matcher.match_verified, a, b, self.verification)] = key

    @property
    def in_flight(self) -> int:
        return len(self.futures)

    def wait(self) -> list[tuple[object, tuple | BaseException]]:
        """Blocks until a pair is finished; returns every finished pair's key and
        ``match_verified`` result (or its error)."""
        done, _ = wait(list(self.futures), return_when=FIRST_COMPLETED)
        return [(self.futures.pop(f), f.exception() or f.result()) for f in done]

    def close(self) -> None:
        for future in self.futures:
            future.cancel()
        self.pool.shutdown(wait=True)

    def describe(self) -> dict:
        return {"name": "local", "workers": self.workers}


def _pair_worker_class():
    import ray

    @ray.remote(num_cpus=1)
    class PairWorker:
        """One matcher per worker process (loaded once), on ``threads`` torch threads."""

        def __init__(self, matcher: Matcher, threads: int, verification: dict):
            import torch

            torch.set_num_threads(threads)
            os.environ["OMP_NUM_THREADS"] = str(threads)
            self.matcher, self.verification = matcher, verification

        def match(self, a: ImageData, b: ImageData) -> tuple:
            return self.matcher.match_verified(a, b, self.verification)

    return PairWorker


class RayExecutor:
    """Pairs matched by actors on a Ray cluster; the driver (this process) stays the only database
    writer."""

    def __init__(
        self,
        matcher: Matcher,
        address: str | None = None,
        num_cpus: int | None = None,
        tasks_per_worker: int = 2,
        verification: dict | None = None,
    ):
        try:
            import ray
        except ImportError as err:
            raise RuntimeError(
                "--executor ray needs Ray: pip install 'colmap_guided[ray]' (or pip install ray)."
            ) from err
        self.ray = ray
        address = address or os.environ.get("RAY_ADDRESS") or None
        self.owns = not ray.is_initialized()
        if self.owns:
            if address is None:  # a private instance: address="local" never joins a running cluster
                cores = (
                    len(os.sched_getaffinity(0))
                    if hasattr(os, "sched_getaffinity")
                    else os.cpu_count() or 1
                )
                # Ray runs workers at nice +15 by default: beside any other work they starve while
                # the driver waits (4x fewer pairs/s than the local threads here). The pairs are the
                # user's work: same priority.
                saved = os.environ.get("RAY_worker_niceness")
                os.environ.setdefault("RAY_worker_niceness", "0")
                try:
                    ray.init(
                        address="local",
                        num_cpus=num_cpus or cores,
                        include_dashboard=False,
                        log_to_driver=False,
                        configure_logging=False,
                    )
                finally:
                    if saved is None:
                        os.environ.pop("RAY_worker_niceness")
            else:
                try:
                    ray.init(address=address, log_to_driver=False, configure_logging=False)
                except Exception as err:  # noqa: BLE001
                    # Ray raises ConnectionError, RuntimeError, AuthenticationError
                    raise RuntimeError(
                        f"Could not connect to the Ray cluster at {address} ({err}); "
                        "start it with `ray start --head` and pass its address, or "
                        "omit --ray_address for a private local instance."
                    ) from err
        self.workers: list = []
        self.refs: dict = {}  # object ref -> (key, worker index)
        try:
            cpus = int(ray.cluster_resources().get("CPU", 1))
            worker_class = _pair_worker_class()
            shipped = ray.put(matcher)
            self.workers = [
                worker_class.remote(shipped, matcher.torch_threads or 1, verification or {})
                for _ in range(max(1, cpus))
            ]
        except BaseException:
            self.close()
            raise
        self.num_workers = len(self.workers)
        self.capacity = tasks_per_worker * self.num_workers
        self.load = [0] * len(self.workers)
        logger.info(
            "Ray: %d pair workers on %s",
            len(self.workers),
            "a private local instance"
            if self.owns and address is None
            else address or "the running Ray session",
        )

    def put(self, image: ImageData):
        return self.ray.put(image)

    def submit(self, key, a, b) -> None:
        worker = min(range(len(self.workers)), key=self.load.__getitem__)  # the least loaded actor
        self.load[worker] += 1
        self.refs[self.workers[worker].match.remote(a, b)] = (key, worker)

    @property
    def in_flight(self) -> int:
        return len(self.refs)

    def wait(self) -> list[tuple[object, tuple | BaseException]]:
        ready, _ = self.ray.wait(list(self.refs), num_returns=1)
        ready += (
            self.ray.wait(
                [r for r in self.refs if r not in ready],
                num_returns=len(self.refs) - len(ready),
                timeout=0,
            )[0]
            if len(self.refs) > 1
            else []
        )
        out = []
        for ref in ready:
            key, worker = self.refs.pop(ref)
            self.load[worker] -= 1
            try:
                out.append((key, self.ray.get(ref)))
            except Exception as err:  # noqa: BLE001
                # the matcher's error (RayTaskError subclasses it), or a lost worker
                out.append((key, err))
        return out

    def close(self) -> None:
        for ref in self.refs:
            try:
                self.ray.cancel(ref)
            except Exception:  # noqa: BLE001 - already finished or its worker gone
                pass
        self.refs.clear()
        for worker in self.workers:
            self.ray.kill(worker)
        self.workers = []
        if self.owns and self.ray.is_initialized():
            self.ray.shutdown()

    def describe(self) -> dict:
        return {"name": "ray", "workers": self.num_workers}


def get_executor(
    name: str, matcher: Matcher, address: str | None = None, verification: dict | None = None
):
    """``verification``: the options of ``verify.two_view_options`` that a matcher verifying its
    own matches (``Matcher.match_verified``) uses."""
    if name == "local":
        if address:
            raise ValueError("--ray_address applies to --executor ray only.")
        return LocalExecutor(matcher, verification)
    if name == "ray":
        return RayExecutor(matcher, address, verification=verification)
    raise ValueError(f"Unknown executor {name!r}; choose one of {', '.join(EXECUTORS)}.")
