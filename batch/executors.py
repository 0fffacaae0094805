"""Executors run jobs; they know nothing about stages.

An executor takes `submit(key, fn, arg, resources, priority)` and hands back finished jobs
from `wait()` as (key, result) pairs, `result` being what `fn(arg)` returned or the exception
that stopped it for good (after the executor's retries). Ordering and dependencies are the
scheduler's: it only submits jobs whose inputs are done.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Hashable
from typing import Any, Protocol

#: Environment variables a job reads, passed to Ray workers (a worker on another machine does
#: not inherit the driver's environment).
FORWARDED_ENV = ("PANO_PIPE_MAX_MEGAPIXELS", "PANO_PIPE_CACHE", "PANO_PIPE_BUILD_WAIT", "PANO_PIPE_MARCH",
                 "PANO_PIPE_LPIPS_WEIGHTS", "PANO_PIPE_INJECT_KILL_ONCE")


#: Seconds to wait for a Ray cluster at --address (`--connect-timeout`); Ray itself retries for
#: minutes, silently.
DEFAULT_CONNECT_TIMEOUT = 30.0


def _host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of a Ray address ("host:port", "ray://host:port"), or None when it names no
    socket ("auto", "local": Ray finds the cluster itself)."""
    from urllib.parse import urlsplit

    text = address if "://" in address else f"ray://{address}"
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError:
        port = None
        parts = None
    if parts is None or not parts.hostname or port is None:
        return None
    return parts.hostname, port


def check_reachable(address: str, timeout: float) -> None:
    """Refuse, in one line, a Ray address nothing answers at within `timeout` seconds."""
    import socket

    from runfs.errors import PanoError

    if address in ("auto", "local"):
        return
    host_port = _host_port(address)
    if host_port is None:
        raise PanoError("--address", f"{address!r} is not HOST:PORT, ray://HOST:PORT or auto")
    try:
        socket.create_connection(host_port, timeout=timeout).close()
    except OSError as e:
        why = "timed out" if isinstance(e, TimeoutError) else (e.strerror or str(e))
        raise PanoError("--address", f"cannot reach a Ray cluster at {address}: {why} "
                                     f"(within {timeout:g} s; --connect-timeout)") from None


@contextlib.contextmanager
def bounded_connect(seconds: float | None, problem: str):
    """Run the block (ray.init) with Ray's C++ log kept off stderr, and end the process with the
    one line `error: --address: <problem>` (exit 2) if it runs longer than `seconds`. ray.init
    blocks in C++ retrying an address where something other than Ray listens, where no Python
    signal handler runs; nothing is written before it (the batch has not started), so the
    watchdog may end the process at once."""
    import tempfile
    import threading

    saved = os.dup(2)
    log = tempfile.TemporaryFile()
    os.dup2(log.fileno(), 2)
    done = threading.Event()

    def watchdog() -> None:
        if seconds is not None and not done.wait(seconds):
            os.write(saved, f"error: --address: {problem}\n".encode())
            os._exit(2)

    threading.Thread(target=watchdog, name="ray-connect-timeout", daemon=True).start()
    try:
        yield
    finally:
        done.set()
        os.dup2(saved, 2)
        os.close(saved)
        log.close()


class Executor(Protocol):
    name: str
    #: Whether jobs run side by side, each limited to the CPUs it asked for.
    shares_cores: bool
    #: Whether wait() calls on_start when a job starts (else the scheduler reads run logs).
    reports_start: bool

    def submit(self, key: Hashable, fn: Callable[[Any], Any], arg: Any, resources: dict[str, float],
               priority: tuple = ()) -> None: ...

    def wait(self, timeout: float, on_start: Callable[[Hashable], None] | None = None
             ) -> list[tuple[Hashable, Any]]:
        """Finished jobs, waiting up to `timeout` s for one; `on_start(key)` where the executor
        knows when a job starts (the scheduler also reads it from the run log)."""
        ...

    def cancel(self) -> None: ...

    def close(self) -> None: ...


class LocalExecutor:
    """This process, one job at a time, lowest priority first (the scheduler's order: a scene's
    stages one after another, then the next scene). A job has all the machine's cores."""

    name = "local"
    shares_cores = False
    reports_start = True

    def __init__(self):
        self._queue: list[tuple[tuple, int, Hashable, Callable, Any]] = []
        self._count = 0

    def submit(self, key, fn, arg, resources, priority=()):
        self._count += 1
        self._queue.append((priority, self._count, key, fn, arg))

    def wait(self, timeout, on_start=None):
        if not self._queue:
            return []
        item = min(self._queue, key=lambda q: (q[0], q[1]))
        self._queue.remove(item)
        _, _, key, fn, arg = item
        if on_start is not None:
            on_start(key)
        try:
            return [(key, fn(arg))]
        except Exception as e:  # noqa: BLE001 (the job's own failure: reported, the batch goes on)
            return [(key, e)]

    def cancel(self) -> None:
        self._queue.clear()

    def close(self) -> None:
        pass


class RayExecutor:
    """Each job a Ray task. A task whose worker dies (killed, out of memory, a lost node) is
    retried up to `retries` times by Ray; a job's own failure comes back as its result and is
    not retried (bad input stays bad)."""

    name = "ray"
    shares_cores = True
    reports_start = False

    def __init__(self, address: str | None = None, num_cpus: int | None = None, retries: int = 2,
                 connect_timeout: float = DEFAULT_CONNECT_TIMEOUT):
        # Ray's C++ core logs warnings straight to stderr, which holds only our error line
        # (docs/security.md); while connecting they are diverted (bounded_connect)
        os.environ.setdefault("RAY_BACKEND_LOG_LEVEL", "error")
        if address:
            check_reachable(address, connect_timeout)
        try:
            import ray
        except ImportError:
            from runfs.errors import PanoError

            raise PanoError("--executor ray", "Ray is not installed: pip install 'pano-pipe[ray]'") from None
        self._ray = ray
        self.retries = retries
        env = {k: os.environ[k] for k in FORWARDED_ENV if k in os.environ}
        #: per task only where Ray was started by someone else (a task's own runtime_env costs
        #: it a dedicated worker)
        self._task_env = None
        if not ray.is_initialized():
            # Ray's own INFO/WARNING lines would land on stderr, which holds only errors (docs/security.md)
            kwargs: dict[str, Any] = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR,
                                          runtime_env={"env_vars": env} if env else None)
            if address:
                kwargs["address"] = address
            elif num_cpus:
                kwargs["num_cpus"] = num_cpus
            with bounded_connect(connect_timeout if address else None,
                                 f"no Ray cluster answered at {address} within {connect_timeout:g} s "
                                 "(something else listens there?); check --address, or raise --connect-timeout"):
                ray.init(**kwargs)
            self._owns_ray = True
        else:
            self._owns_ray = False
            self._task_env = {"env_vars": env} if env else None
        self._tasks: dict[Any, Hashable] = {}
        self._remote = {}

    def _remote_fn(self, fn):
        if fn not in self._remote:
            self._remote[fn] = self._ray.remote(fn)
        return self._remote[fn]

    def submit(self, key, fn, arg, resources, priority=()):
        opts = {"num_cpus": resources.get("CPU", 1), "num_gpus": resources.get("GPU", 0),
                "max_retries": self.retries, "retry_exceptions": False}
        if self._task_env:
            opts["runtime_env"] = self._task_env
        ref = self._remote_fn(fn).options(**opts).remote(arg)
        self._tasks[ref] = key

    def wait(self, timeout, on_start=None):
        if not self._tasks:
            return []
        done, _ = self._ray.wait(list(self._tasks), num_returns=len(self._tasks), timeout=timeout)
        out = []
        for ref in done:
            key = self._tasks.pop(ref)
            try:
                out.append((key, self._ray.get(ref)))
            except Exception as e:  # noqa: BLE001 (a worker that kept dying, a lost object)
                out.append((key, e))
        return out

    def cancel(self) -> None:
        for ref in list(self._tasks):
            try:
                self._ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001 (already finished)
                pass
        self._tasks.clear()

    def close(self) -> None:
        if self._owns_ray:
            self._ray.shutdown()


def make_executor(name: str, address: str | None = None, num_cpus: int | None = None,
                  retries: int = 2, connect_timeout: float = DEFAULT_CONNECT_TIMEOUT) -> Executor:
    if name == "local":
        return LocalExecutor()
    if name == "ray":
        return RayExecutor(address, num_cpus, retries, connect_timeout)
    from runfs.errors import PanoError

    raise PanoError("--executor", f"must be local or ray, got {name!r}")
