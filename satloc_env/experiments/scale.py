"""Scale-out on Ray: the experiments' independent units as Ray tasks, simulator environments in Ray actors.

Ray is optional (``pip install -e '.[ray]'``) and imported only here, when it is asked for.

**Units.** :func:`satloc_env.experiments.tables.table1`, :func:`~satloc_env.experiments.tables.table2` and
:func:`~satloc_env.experiments.tables.sweep` cut their work into :class:`Unit` s (a module-level function and its
arguments, called as ``fn(*args, progress=..., log=...)``) that write disjoint files of the output folder, and
hand lists of them to a :class:`Runner`:

* ``Runner()`` (the default) calls them one after the other in this process, as the experiments always did;
* ``Runner(ray=True, address=...)`` (``satloc experiment ... --ray [ADDRESS]``) submits them as Ray remote
  tasks (``ray.init()``: a local cluster of this machine's cores; ``ray.init(address=ADDRESS)``: an existing
  cluster, e.g. ``auto`` after ``ray start --head``) and returns their results in the order of the list.

A task runs in a Ray worker process, which raylet starts fresh (not a ``fork`` of the driver), so it may
render (:mod:`satloc_env.render.gl`). It asks for ``cpus`` = the cluster's CPUs shared over the units (at least one)
and runs OpenCV and the GL rasterizer (llvmpipe) on as many threads (:func:`set_threads`). torch and the BLAS
libraries keep the thread counts of the driver (a serial run) by default, because their sums depend on the
thread count (measured: the projections learned with torch or BLAS on 1 thread instead of 2 differ by up to
1.2e-4, which moved a mean error in ``sweep.csv`` from 13.17 to 13.29 m): the tables are then byte-identical to a serial run's on
the driver's machine (and on nodes of the same CPU type), at the price of more threads than cores while
several tasks run torch or BLAS (their idle threads sleep instead of spinning: :data:`WORKER_ENV`). ``Runner(exact=False)`` (``--ray-threads cpus``) runs them on the task's
CPUs too: no oversubscription, numbers that may differ from the serial run's in the last digits.

Progress bars are off in a task; its log lines come back with its result and the driver prints them when it
finishes. The workers run in the driver's working directory where they have it (relative ``--out`` and scene
paths); on several machines the output folder must be one shared file system at the same path on every node.

**Environment actors.** :class:`EnvActor` holds a ``satloc/SatLoc-v0`` environment (or a batched
``gym.make_vec`` one) in a Ray actor, for a runner that steps many environments on many cores or machines::

    import ray
    from satloc_env.experiments.scale import env_actor

    ray.init()
    cars = [env_actor(scene="city", localizer=None) for _ in range(4)]       # one process, one CPU each
    first = ray.get([c.reset.remote(seed=i) for i, c in enumerate(cars)])  # [(obs, info), ...]
    actions = ray.get([c.autopilot_action.remote() for c in cars])         # or the agent's
    steps = ray.get([c.step.remote(a) for c, a in zip(cars, actions)])     # [(obs, reward, term, trunc, info)]
    batched = env_actor(num_envs=8, num_cpus=2, scene="city", localizer=None)  # gym.make_vec in one actor
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from satloc.errors import ConfigError, SatlocError

if TYPE_CHECKING:
    from typing_extensions import Self

R = TypeVar("R")

INSTALL_HINT = "pip install -e '.[ray]' (or pip install 'ray>=2.9')"


def import_ray():
    """The ``ray`` module; :class:`ConfigError` with the install command when it is not installed."""
    try:
        import ray
    except ImportError as e:
        raise ConfigError(f"--ray: Ray is not installed ({e}); install it with {INSTALL_HINT}") from None
    return ray


@dataclass(frozen=True)
class Unit(Generic[R]):
    """One independent piece of an experiment: ``fn(*args, progress=progress, log=log)``. ``fn`` is a
    module-level function (Ray ships it by name) and writes only files no other unit of its list writes."""

    name: str
    fn: Callable[..., R]
    args: tuple = ()

    def __call__(self, progress: bool, log: Callable[[str], None]) -> R:
        return self.fn(*self.args, progress=progress, log=log)


#: the environment of the task processes: thread pools that sleep at once when idle (OpenMP: torch, MKL, faiss;
#: OpenBLAS) instead of spinning for a while, since several tasks' pools share the cores (how threads wait
#: changes no result; measured on 2 cores, a 4-combination sweep on Ray: 146 s without, 123 s with it, serial
#: 156 s); a variable set in the driver's environment is left as it is
WORKER_ENV = {"OMP_WAIT_POLICY": "PASSIVE", "OPENBLAS_THREAD_TIMEOUT": "4"}


def thread_counts() -> dict[str, int]:
    """This process's thread counts: torch's, and per threadpoolctl API (``blas``, ``openmp``) the largest of
    its loaded libraries'."""
    import torch
    from threadpoolctl import threadpool_info

    counts = {"torch": torch.get_num_threads()}
    for lib in threadpool_info():
        counts[lib["user_api"]] = max(counts.get(lib["user_api"], 1), int(lib["num_threads"]))
    return counts


def set_threads(cpus: int, counts: dict[str, int] | None = None) -> None:
    """OpenCV and the GL rasterizer (llvmpipe; contexts made from now on) on ``cpus`` threads; torch and the
    BLAS / OpenMP libraries (threadpoolctl APIs) as in ``counts`` (:func:`thread_counts`; None: ``cpus``)."""
    import cv2
    import faiss  # noqa: F401  (its OpenMP runtime loaded, so that threadpoolctl sets it too)
    import torch
    from threadpoolctl import threadpool_limits

    cpus = max(1, int(cpus))
    counts = counts or {"torch": cpus, "blas": cpus, "openmp": cpus}
    os.environ["LP_NUM_THREADS"] = str(cpus)
    cv2.setNumThreads(cpus)
    threadpool_limits(limits={api: n for api, n in counts.items() if api != "torch"})
    torch.set_num_threads(counts["torch"])   # after threadpoolctl, which sets torch's OpenMP runtime too


def _run_unit(unit: Unit, cpus: int, counts: dict[str, int] | None, cwd: str) -> tuple[Any, list[str], float]:
    """A unit in a Ray worker: its result, its log lines and its wall time (seconds)."""
    if cwd:
        if not os.path.isdir(cwd):   # relative paths (--out) would land somewhere else on this node
            raise ConfigError(f"Ray task {unit.name}: the driver's working directory {cwd} does not exist on this "
                              "node; run from a folder on a file system every node shares, at the same path")
        os.chdir(cwd)
    set_threads(cpus, counts)
    lines: list[str] = []
    t = time.perf_counter()
    result = unit(False, lines.append)
    return result, lines, time.perf_counter() - t


def _address(address: str | None) -> str:
    """What ``ray.init`` gets: ``address``, else the cluster ``RAY_ADDRESS`` names, else ``"local"`` (a new local
    cluster; ``ray.init()`` without an address would join one that ``ray start`` left running here)."""
    return address or os.environ.get("RAY_ADDRESS") or "local"


class Runner:
    """Runs lists of :class:`Unit` s: serially here (``ray=False``), or as Ray tasks on the cluster at
    ``address`` (None: a new local cluster, or the one ``RAY_ADDRESS`` names; never a cluster this machine's
    ``ray start`` left running, which ``ray.init()`` alone would join). A Ray
    already initialized in this process is used as it is; one this runner started is shut down by
    :meth:`close` (or at the end of a ``with`` block). ``exact``: the tasks' torch and BLAS thread counts are
    this process's (results identical to a serial run), else the task's CPUs (see the module's docstring)."""

    def __init__(self, ray: bool = False, address: str | None = None, exact: bool = True):
        self.ray = bool(ray)
        self.address = address or None
        self.exact = exact
        self._started = False
        if self.ray:
            import_ray()   # before any work: a clear error when it is missing

    @property
    def parallel(self) -> bool:
        return self.ray

    def _init(self):
        ray = import_ray()
        if not ray.is_initialized():
            try:
                ray.init(address=_address(self.address), logging_level="WARNING")
            except (ConnectionError, ValueError) as e:
                raise ConfigError(f"--ray {_address(self.address)}: cannot connect to a Ray cluster there ({e}); start "
                                  "one with `ray start --head`, or give --ray without an address for a local "
                                  "one. A cluster that `ray start` made with token authentication (the default "
                                  "since Ray 2.59) needs RAY_AUTH_MODE=token here, and its token (`ray "
                                  "get-auth-token` on the head) in RAY_AUTH_TOKEN on another machine") from None
            self._started = True
        return ray

    def cpus_per_unit(self, n_units: int) -> int:
        """The CPUs (and threads) of each of ``n_units`` tasks: the cluster's CPUs shared over them, at least
        one, at most the CPUs of its largest node."""
        ray = self._init()
        total = int(ray.cluster_resources().get("CPU", 1))
        node = max((int(n["Resources"].get("CPU", 0)) for n in ray.nodes() if n.get("Alive")), default=1)
        return max(1, min(node, total // max(1, n_units)))

    def run(self, units: list[Unit[R]], progress: bool = True, log=print) -> list[R]:
        """Each unit's result, in the order of ``units``."""
        if not self.ray:
            return [u(progress, log) for u in units]
        if not units:
            return []
        ray = self._init()
        cpus = self.cpus_per_unit(len(units))
        env = {k: v for k, v in WORKER_ENV.items() if k not in os.environ}
        task = ray.remote(_run_unit).options(num_cpus=cpus, **({"runtime_env": {"env_vars": env}} if env else {}))
        counts = thread_counts() if self.exact else None
        refs = [task.remote(u, cpus, counts, os.getcwd()) for u in units]
        pending = {r: i for i, r in enumerate(refs)}
        results: list = [None] * len(units)
        log(f"[ray] {len(units)} unit(s), {cpus} CPU(s) each: " + ", ".join(u.name for u in units))
        try:
            while pending:
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                i = pending.pop(ref)
                try:
                    results[i], lines, secs = ray.get(ref)
                except ray.exceptions.RayTaskError as e:
                    if isinstance(e.cause, SatlocError):   # bad input: one line, as without Ray
                        raise e.cause from None
                    raise
                for line in lines:
                    log(line)
                log(f"[ray] {units[i].name}: done in {secs:.1f} s ({len(units) - len(pending)}/{len(units)})")
        except BaseException:
            for ref in pending:   # the rest would run on for nothing (finished stages stay; a rerun resumes)
                ray.cancel(ref)
            raise
        return results

    def close(self) -> None:
        if self._started:
            import_ray().shutdown()
            self._started = False

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- environments in Ray actors ----------------------------------------------------------------------------------

class EnvActor:
    """A ``satloc/SatLoc-v0`` environment in one process: ``gym.make(ENV_ID, **kwargs)``, or with ``num_envs``
    the batched ``gym.make_vec(ENV_ID, num_envs, **kwargs)``. Use it through :func:`env_actor` (a Ray
    actor); its methods return what the environment returns (numpy arrays and plain values)."""

    def __init__(self, num_envs: int | None = None, threads: int = 1, **kwargs):
        import gymnasium as gym

        from satloc_env.envs import ENV_ID

        set_threads(threads)
        self.env = (gym.make(ENV_ID, **kwargs) if num_envs is None else
                    gym.make_vec(ENV_ID, num_envs, **kwargs))

    def reset(self, seed=None, options: dict | None = None):
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        return self.env.step(action)

    def spaces(self):
        """``(observation_space, action_space)``."""
        return self.env.observation_space, self.env.action_space

    def autopilot_action(self):
        """The autopilot's action(s) for the current state (one env: (2,); batched: (num_envs, 2))."""
        u = self.env.unwrapped
        return u.autopilot_actions() if hasattr(u, "autopilot_actions") else u.autopilot_action()

    def close(self) -> None:
        self.env.close()


def env_actor(num_envs: int | None = None, num_cpus: int = 1, **kwargs):
    """A Ray actor holding an :class:`EnvActor` with ``num_cpus`` CPUs (and as many threads); ``kwargs``
    go to ``gym.make``/``gym.make_vec``. Call its methods with ``.remote(...)`` and ``ray.get`` the results.
    Arrays that ``ray.get`` returns are read-only views of Ray's object store (a local environment's are
    writable): copy one (``np.array(obs["left"])``) before changing it in place. Without a Ray in this process
    it starts a new local one (or joins the cluster ``RAY_ADDRESS`` names), as :class:`Runner` does."""
    ray = import_ray()
    if not ray.is_initialized():
        ray.init(address=_address(None), logging_level="WARNING")
    return ray.remote(EnvActor).options(num_cpus=num_cpus).remote(num_envs, num_cpus, **kwargs)

