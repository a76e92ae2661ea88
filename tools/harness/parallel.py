"""Running a command's cases (validate's comparisons, stability's cases, check's images) in
this process or on Dask workers, with the results in the cases' order.

* In this process (``Plan.in_process``: ``--serial``, ``--workers 0`` or ``1``): a plain loop,
  no Dask.
* A local cluster (the default for a run long enough, where its serial run would leave
  cores idle: ``Plan.resolve``): ``distributed.LocalCluster`` of one worker process per
  core, one Dask thread each.  Its scratch directory is a temporary one, removed when the run
  ends, however it ends (Ctrl-C, SIGTERM, an error).
* An existing cluster (``--scheduler ADDRESS``): its workers must run the same rtval, Dr.Jit
  and Mitsuba (checked before any case is sent).

Every case runs through ``_call`` on a worker: the first one in a worker process sets it up
(imports, Dr.Jit's backend and its thread count, Mitsuba's variant; ``worker_setup``), so a
worker keeps its compiled kernels (Dr.Jit caches them per process) from one case to the next.
Dr.Jit's LLVM backend runs its own thread pool in each worker: it gets the worker's share of
its machine's cores (``drjit_threads``), so that the workers do not oversubscribe them.  A
case's exception comes back as a value and is raised here as the serial run would raise it:
the one of the earliest case, with the same one-line message; a worker that dies is one line
too.  Workers never write files: what a case produces comes back to this process, which
writes.
"""
from __future__ import annotations

import contextlib
import itertools
import logging
import os
import pickle
import shutil
import signal
import threading
import traceback
from collections import Counter
from dataclasses import dataclass

from rt_core.usererror import InputError


class ClusterError(InputError):
    """The Dask cluster cannot be reached or used, or lost a worker; one line."""
    exit_code = 2


class CaseError(InputError):
    """A user error (bad scene, unreadable file, ...) raised by a case on a worker whose
    exception does not survive pickling: the same one line, the same exit code."""

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code

    def __reduce__(self):
        return CaseError, (str(self), self.exit_code)


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@dataclass(frozen=True)
class Plan:
    """Where the cases run: ``workers`` None = one per core; 0 or 1 = in this process;
    ``scheduler`` an existing cluster's address (then ``workers`` is ignored)."""
    workers: int | None = None
    scheduler: str | None = None
    verbose: bool = False

    @property
    def local_workers(self) -> int:
        return cores() if self.workers is None else self.workers

    @property
    def in_process(self) -> bool:
        return self.scheduler is None and self.local_workers <= 1

    def resolve(self, n: int | None, seconds_per_case: float = 1.0,
                busy_cores: float = 1.0) -> "Plan":
        """The plan a run of ``n`` cases uses: by default (``workers`` None, no scheduler)
        a run stays in this process when it would leave less than IDLE_MIN_CORES of the
        machine's cores idle there (``busy_cores``: the cores the command's serial run
        keeps busy, measured), when it would take less than AUTO_MIN_SECONDS there
        (``seconds_per_case``: the command's rough estimate), or when it has one case."""
        if self.workers is None and self.scheduler is None and (
                cores() - busy_cores < IDLE_MIN_CORES or
                (n is not None and (n < 2 or n * seconds_per_case < AUTO_MIN_SECONDS))):
            return Plan(0, None, self.verbose)
        return self

    def describe(self) -> str:
        if self.scheduler:
            return f"Dask cluster {self.scheduler}"
        if self.in_process:
            return "in this process"
        return f"local Dask cluster of {self.local_workers} worker processes"


SERIAL = Plan(workers=0)
# by default a shorter run stays in this process: a local cluster of 2 workers costs about
# 3 s before its first result and 5 CPU seconds (each worker imports Dask, Dr.Jit and
# Mitsuba), more than a short run gains on 2 cores (benchmarks/parallel_speedup.py)
AUTO_MIN_SECONDS = 30.0
# and so does a run whose serial run leaves less than this many cores idle: on 2 cores the
# default validate keeps 1.8 busy (Dr.Jit's and Mitsuba's threads) and ran 1.25x faster
# serial than on 2 workers, stability keeps 1.06 busy and ran 1.31x faster on 2 workers
# (benchmarks/parallel_speedup.py, README "Many cores, many machines")
IDLE_MIN_CORES = 0.5


def plan_of(args) -> Plan:
    """The Plan of parsed options (``tools.options.add_parallel``)."""
    workers = 0 if getattr(args, "serial", False) else getattr(args, "workers", None)
    return Plan(workers, getattr(args, "scheduler", None), getattr(args, "verbose", False))


# --- on a worker ----------------------------------------------------------------------------

_STATE = {"setups": 0, "cases": 0, "kernels": Counter(), "loaded": Counter()}
_LOCK = threading.Lock()        # one case at a time per process (Dr.Jit, Mitsuba: one user)


# Dr.Jit's thread pool on a worker: never 1.  With one thread, Mitsuba's ray_intersect gives
# other answers on rays exactly through a shared edge than with 2, 3, 4, 8 or 16 (measured:
# rtval stability's edges[2^-40], Mitsuba 66 mismatches instead of 107; every other case of
# the full sweep agrees), and the serial run uses Dr.Jit's default, one thread per core.
MIN_DRJIT_THREADS = 2


def drjit_threads(cores: int, workers: int) -> int:
    """Dr.Jit threads of a worker: its machine's cores shared out among the workers there,
    at least MIN_DRJIT_THREADS."""
    return max(MIN_DRJIT_THREADS, cores // max(workers, 1))


def worker_setup(threads: int | None = None) -> None:
    """Once per process: import the tracer and the references, check Dr.Jit's LLVM backend,
    set its thread count to ``threads`` (None: Dr.Jit's default), select Mitsuba's variant.
    Later calls return at once."""
    if _STATE["setups"]:
        return
    _STATE["setups"] += 1
    import drjit as dr
    from rt_core import backend
    backend.require("llvm")
    if threads:
        dr.set_thread_count(threads)
    from mitsuba_ref.convert import mitsuba
    mitsuba()
    import tools.harness.check  # noqa: F401  (the cases' modules: imported once, here)
    import tools.harness.stability  # noqa: F401
    import tools.harness.validate  # noqa: F401


def _count_kernels() -> None:
    """Drain Dr.Jit's kernel history into _STATE: JIT kernels compiled, loaded from the disk
    cache, found in memory; and how often each kernel was loaded (compiled or from disk)."""
    import drjit as dr
    for e in dr.kernel_history():
        if e["type"] != dr.KernelType.JIT:
            continue
        # (a kernel read from the disk cache has cache_hit set too)
        how = "disk" if e["cache_disk"] else "memory" if e["cache_hit"] else "compiled"
        _STATE["kernels"][how] += 1
        if how != "memory":
            _STATE["loaded"][e["hash"]] += 1


def _call(fn, item, config: dict):
    """Run one case on a worker: ("ok", result) or ("raised", exception)."""
    with _LOCK:
        worker_setup(_threads_here(config.get("workers_per_host", {})))
        _STATE["cases"] += 1
        count = config.get("count_kernels", False)
        if count:
            import drjit as dr
            dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            return "ok", fn(item)
        except Exception as exc:            # noqa: BLE001 -- it becomes the case's outcome
            return "raised", _portable(exc)
        finally:
            if count:
                _count_kernels()
                dr.set_flag(dr.JitFlag.KernelHistory, False)


def _threads_here(workers_per_host: dict) -> int | None:
    """This worker's Dr.Jit threads: ``drjit_threads`` of the cores here and the number of
    workers on this host (``workers_per_host``, from the scheduler when the run began; for
    a worker that joined later, as many as its Dask threads fit in the cores)."""
    try:
        from distributed import get_worker
        from distributed.comm import get_address_host
        w = get_worker()
        n = workers_per_host.get(get_address_host(w.address))
    except (ImportError, ValueError, AttributeError):
        return None
    return drjit_threads(cores(), n or max(1, cores() // max(w.state.nthreads, 1)))


def _portable(exc: Exception) -> Exception:
    """``exc`` as it can travel back: itself when it survives pickling with its message,
    else a CaseError (a user error: same line and exit code) or a RuntimeError naming it.
    A bug's worker-side traceback is kept as a note."""
    from rt_core.errors import USER_ERRORS
    user = isinstance(exc, USER_ERRORS)
    if not user:
        note = "on a Dask worker:\n" + "".join(traceback.format_exception(exc)).rstrip()
        exc.__notes__ = [*getattr(exc, "__notes__", []), note]    # add_note, in 3.10 too
    try:
        back = pickle.loads(pickle.dumps(exc))
        if type(back) is type(exc) and str(back) == str(exc):
            return exc
    except Exception:                       # noqa: BLE001 -- any failure: use the fallback
        pass
    if user:
        return CaseError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__,
                         getattr(exc, "exit_code", 2))
    return RuntimeError(f"{type(exc).__name__}: {exc}\n"
                        + "".join(getattr(exc, "__notes__", [])))


def worker_stats() -> dict:
    """This worker's setups, cases and kernel counts (``reloaded``: kernels compiled or read
    from disk more than once in this process; 0 when the in-memory cache works)."""
    return {"pid": os.getpid(), "setups": _STATE["setups"], "cases": _STATE["cases"],
            "kernels": dict(_STATE["kernels"]),
            "reloaded": sum(n - 1 for n in _STATE["loaded"].values() if n > 1)}


# --- here -----------------------------------------------------------------------------------

def run_cases(fn, items, plan: Plan = SERIAL, each=None, stats: dict | None = None,
              count: int | None = None, seconds_per_case: float = 1.0,
              busy_cores: float = 1.0) -> list:
    """``fn(item)`` for every item, where ``plan`` says.  As each result arrives,
    ``each(index, result)`` is called and what it returns is kept (default: the result);
    returns the kept values in the items' order.

    ``items`` may be a generator: it is drawn as the cases are sent (``check --run`` yields
    each image as the user's tracer writes it).  ``count``: how many it will yield, when
    ``items`` has no len(); with ``seconds_per_case`` and ``busy_cores`` it decides
    whether a default plan uses a local cluster (``Plan.resolve``).  ``stats``: filled with each worker's
    ``worker_stats()`` (Dask only)."""
    each = each or (lambda i, r: r)
    n = len(items) if hasattr(items, "__len__") else count
    plan = plan.resolve(n, seconds_per_case, busy_cores)
    if plan.in_process or n == 0:
        return [each(i, fn(x)) for i, x in enumerate(items)]
    with session(plan, count_kernels=stats is not None or plan.verbose) as (client, config):
        out = _run_on(client, config, fn, items, each)
        if stats is not None or plan.verbose:
            got = client.run(worker_stats)
            if stats is not None:
                stats.update(got)
            if plan.verbose:
                import sys
                for addr, s in sorted(got.items()):
                    print(f"rtval: worker {addr}: {s['cases']} cases, {s['setups']} set-up, "
                          f"kernels {s['kernels']}, loaded twice {s['reloaded']}",
                          file=sys.stderr)
        return out


def _run_on(client, config, fn, items, each) -> list:
    """Send the cases, at most a window of them at a time (a sweep of 100,000 cases does not
    sit in the scheduler at once, nor a generator's items in memory), and consume the results
    as they complete.  After a case raises, the later cases are cancelled (the serial run
    never reaches them) and the earlier ones finish: the earliest error is raised."""
    from distributed import as_completed
    window = max(32, 8 * (sum(client.nthreads().values()) or 1))
    todo = enumerate(items)
    index = {}
    tag = os.urandom(6).hex()               # this run's keys, apart from another client's

    def submit(i, x):
        f = client.submit(_call, fn, x, config, key=f"rtval-case-{i}-{tag}")
        index[f] = i
        return f

    seq = as_completed()
    for i, x in itertools.islice(todo, window):
        seq.add(submit(i, x))
    kept, error, n = {}, None, len(index)
    for f in seq:
        i = index.pop(f)
        if error is not None and i > error[0]:
            continue                        # cancelled: the serial run never reached it
        status, value = _outcome(f, i)
        f.release()
        if status == "raised":
            if error is None or i < error[0]:
                error = (i, value)
                for g, j in list(index.items()):
                    if j > i:
                        g.cancel()
            continue
        kept[i] = each(i, value)
        if error is None:
            nxt = next(todo, None)
            if nxt is not None:
                seq.add(submit(*nxt))
                n += 1
    if error is not None:
        raise error[1]
    return [kept[i] for i in range(n)]


def _outcome(future, i: int):
    """A finished future's (status, value); a lost worker or cluster is a ClusterError."""
    from distributed.client import FutureCancelledError
    try:
        return future.result()
    except FutureCancelledError as exc:
        raise ClusterError(f"case {i + 1} was cancelled by the Dask cluster ({exc})") from None
    except Exception as exc:                # noqa: BLE001 -- KilledWorker, lost scheduler ...
        name = type(exc).__name__
        if name == "KilledWorker":
            raise ClusterError(f"case {i + 1} killed the Dask workers that ran it (a crash or "
                               "out of memory); run it with --serial to see why") from None
        raise ClusterError(f"case {i + 1}: the Dask cluster failed: {name}: "
                           f"{str(exc).splitlines()[0] if str(exc) else ''}") from None


@contextlib.contextmanager
def session(plan: Plan, count_kernels: bool = False):
    """(client, config for _call): a local cluster or a connection to ``plan.scheduler``;
    closed, and the local cluster's scratch directory removed, however the block ends."""
    _quiet(plan.verbose)
    import dask
    from distributed import Client
    cluster = client = scratch = None
    try:
        if not plan.scheduler:
            scratch = _scratch_dir()
        # the scheduler's and the workers' scratch space (default /tmp/dask-scratch-space);
        # workers forked by the fork server (_local_cluster), restarted ones too
        with dask.config.set({"temporary-directory": scratch,
                              "distributed.worker.multiprocessing-method": "forkserver",
                              "distributed.admin.tick.limit": "1h"}):
            if plan.scheduler:
                client = _connect(plan.scheduler)
            else:
                with _signals_deferred():
                    cluster = _local_cluster(plan, scratch)
                client = Client(cluster)
            _check_workers(client, plan)
            hosts = Counter(w["host"] for w in client.scheduler_info()["workers"].values())
            yield client, {"workers_per_host": dict(hosts), "count_kernels": count_kernels}
    finally:
        # (a signal during the shutdown is delivered after it: one that broke off the
        # close left the scratch directory behind; a helper's review)
        with _signals_deferred():
            with contextlib.suppress(Exception):
                if client is not None:
                    client.close(timeout=10)
            with contextlib.suppress(Exception):
                if cluster is not None:
                    cluster.close(timeout=10)
            if scratch:
                shutil.rmtree(scratch, ignore_errors=True)


def _quiet(verbose: bool) -> None:
    """distributed logs to stderr (worker start-up, shutdown, closed connections): only its
    errors, and with --verbose its warnings too (its info, ~70 lines of workers starting and
    stopping around five scenes' verdicts, buried them: an instructor's review)."""
    level = logging.WARNING if verbose else logging.CRITICAL
    for name in ("distributed", "tornado", "asyncio"):
        logging.getLogger(name).setLevel(level)


def _scratch_dir() -> str:
    """A new scratch directory for a local cluster, ``rtval-dask-TAG-PID-*``
    (rt_core.outputs.scratch_dir: what killed runs left is removed first)."""
    from rt_core.outputs import scratch_dir
    return scratch_dir("dask")


def _local_cluster(plan: Plan, scratch: str):
    """A LocalCluster of ``plan.local_workers`` processes, one Dask thread each, no dashboard,
    no memory limit (rtval's own guard checks memory), scratch space in ``scratch``.

    Ctrl-C reaches the whole process group, and this process closes the workers: they must
    ignore it (each would print a KeyboardInterrupt traceback).  They are forked by
    multiprocessing's fork server (``session`` sets Dask's multiprocessing method; a process
    started from here that imports nothing of Dr.Jit, so forking it is safe), which starts
    with SIGINT ignored and passes that on to every worker, one that Dask restarts included;
    here SIGINT is ignored only while the fork server starts."""
    import multiprocessing.forkserver

    from distributed import LocalCluster
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, old)
    return LocalCluster(n_workers=plan.local_workers, threads_per_worker=1,
                        processes=True, dashboard_address=None, memory_limit=0,
                        scheduler_kwargs={"dashboard": False,       # no port 8787
                                          "dashboard_address": "127.0.0.1:0"},
                        silence_logs=logging.WARNING if plan.verbose else logging.CRITICAL,
                        local_directory=scratch, scheduler_port=0, host="127.0.0.1",
                        death_timeout=30)


@contextlib.contextmanager
def _signals_deferred():
    """Ctrl-C, SIGTERM and SIGHUP held back while the block runs, then delivered: the
    LocalCluster constructor interrupted would leave its scheduler, its workers and its
    event-loop thread running (and this process waiting on that thread at exit), since
    there is no cluster object yet to close."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got = []
    sigs = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP]
    old = {sig: signal.signal(sig, lambda signum, frame: got.append(signum)) for sig in sigs}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        if got:
            signal.raise_signal(got[0])         # the usual handler, now that it can clean up


def _connect(address: str):
    """A client of the scheduler at ``address``; a tcp address is tried with a plain socket
    first, so that a refused connection or an unknown host is said at once (Dask retries
    until its timeout, and then says only that it timed out)."""
    import socket
    from distributed import Client
    from distributed.comm import parse_address, parse_host_port
    try:
        protocol, loc = parse_address(address)
        host_port = parse_host_port(loc) if protocol == "tcp" else None
    except (ValueError, TypeError) as exc:
        raise ClusterError(f"--scheduler {address}: not a scheduler address "
                           f"({_first_line(exc)}); expected e.g. tcp://HOST:8786") from None
    try:
        if host_port:
            with socket.create_connection(host_port, timeout=10):
                pass
    except OSError as exc:
        why = exc.strerror or _first_line(exc)
        if isinstance(exc, socket.gaierror):
            why = f"unknown host: {why}"
        raise ClusterError(f"--scheduler {address}: cannot connect ({why.lower()}); start one "
                           "with `dask scheduler` and `dask worker ADDRESS`, or leave "
                           "--scheduler out for a local cluster") from None
    try:
        return Client(address, timeout=15)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"--scheduler {address}: cannot connect ({_first_line(exc)}); start "
                           "one with `dask scheduler` and `dask worker ADDRESS`, or leave "
                           "--scheduler out for a local cluster") from None
    except ValueError as exc:
        raise ClusterError(f"--scheduler {address}: not a scheduler address "
                           f"({_first_line(exc)}); expected e.g. tcp://HOST:8786") from None


def _first_line(exc) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _check_workers(client, plan: Plan) -> None:
    """At least one worker, and every worker on rtval's, Dr.Jit's and Mitsuba's versions."""
    if plan.scheduler:
        try:
            client.wait_for_workers(1, timeout=30)
        except TimeoutError:
            raise ClusterError(f"--scheduler {plan.scheduler}: no worker joined within 30 s; "
                               f"start some with `dask worker {plan.scheduler}`") from None
    here = versions()
    try:
        there = client.run(versions)
        if plan.scheduler:                  # it unpickles the tasks: it needs rtval too
            there["the scheduler"] = client.run_on_scheduler(versions)
    except Exception as exc:                # noqa: BLE001 -- e.g. rtval not importable there
        raise ClusterError(f"the Dask cluster cannot run rtval ({_first_line(exc)}); start "
                           "its scheduler and workers in rtval's environment") from None
    for addr, v in sorted(there.items()):
        if v != here:
            diff = ", ".join(f"{k} {v.get(k)} (here {here[k]})" for k in here
                             if v.get(k) != here[k])
            raise ClusterError(f"Dask {'worker ' if '://' in addr else ''}{addr} runs {diff}: "
                               "its results could differ from this rtval's; install the same "
                               "versions there")


def versions() -> dict:
    """What must agree between this process and the workers: the libraries' versions and
    rtval's own sources (a hash of its .py files: the package version alone does not change
    from one commit to the next)."""
    import hashlib
    from importlib import metadata
    from pathlib import Path

    def v(name):
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "none"
    root = Path(__file__).resolve().parents[2]
    h = hashlib.sha256()
    for pkg in ("rt_core", "mitsuba_ref", "tools"):
        for f in sorted((root / pkg).rglob("*.py")):
            h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes())
    return {"rtval sources": h.hexdigest()[:12], "drjit": v("drjit"), "mitsuba": v("mitsuba"),
            "numpy": v("numpy")}
