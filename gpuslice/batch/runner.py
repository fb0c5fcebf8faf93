"""Batch execution: :class:`BatchRunner` hands one task per model (:func:`gpuslice.batch.task.run_model`) to this
process (``workers=0``), to local worker processes (one OpenCL context and one kernel build per worker; a failed
model is retried once on another worker unless its content or options are at fault; a worker that dies is replaced and
its unfinished models re-run) or to a Dask ``distributed.Client`` (the scheduler re-runs a lost worker's tasks;
failed models are retried as locally), and collects their records into the batch report (:meth:`BatchRunner.report`).

Skipping: a model whose output exists is skipped (``force`` redoes it); outputs are only renamed into place complete
(with ``--check``, its report must exist too). The output folder's manifest (``.gpuslice-batch.json``) holds the
options that shape the outputs: other options are refused unless ``force``, so a re-run never skips an output of
other options; so are outputs in a folder without a manifest (by name), and files the batch's journal
(:mod:`.journal`) does not list as they are (put there later, or changed since).
"""

from __future__ import annotations

import collections
import contextlib
import json
import numbers
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import BatchError, one_line
from ..io.atomic import atomic_write_tree, remove_path
from .discover import Model, discover
from .journal import (
    JOURNAL_NAME,
    forget_journal,
    read_journal,
    record_finished,
    record_written_since,
    remove_journaled,
    unchanged,
)
from .options import BatchOptions, check_path, same_options
from .pool import Slot, helpers_ignoring_sighup, mp_context, stop_slots
from .report import checks_summary
from .task import _cores, _worker_device, default_workers, init_worker, pocl_thread_env, run_model

__all__ = ["BatchRunner", "MANIFEST_NAME", "run_batch"]

#: the most local worker processes (and PoCL threads per worker) a batch takes
MAX_LOCAL = 1024

#: the manifest in the output folder: the options that shape the outputs
MANIFEST_NAME = ".gpuslice-batch.json"
#: tasks a local worker holds (running and queued): one, so that a model never waits behind a long one on a worker
#: while another worker is idle (two, to hide the round trip between models, measured: 4 models of 0.1-1.5 s on 2
#: workers 1.19x slower; 26 small ones the same, 0.99x; BENCHMARKS, twenty-third session)
PREFETCH = 1
#: a model whose worker died this many times is reported failed instead of re-run again
MAX_LOST = 2



@dataclass
class _Task:
    index: int
    attempt: int = 1
    lost: int = 0
    avoid: str | None = None  # the worker a failed first attempt ran on
    errors: list[str] = field(default_factory=list)
    workers: list[str] = field(default_factory=list)  # the workers of earlier attempts


class BatchRunner:
    """Run one batch: ``BatchRunner(models, opts, out_dir).run(workers=…)`` or ``.run(client=…)``.

    ``progress`` is called with each finished model's record (in the driver process). After ``run`` (or after it
    was interrupted), :meth:`report` gives the batch report.
    """

    def __init__(self, models: Sequence[Model], opts: BatchOptions, out_dir: str | os.PathLike, *,
                 force: bool = False, progress: Callable[[dict], None] | None = None,
                 inputs: Sequence[str] = ()) -> None:
        self.models = list(models)
        self.opts = opts
        self.out_dir = Path(os.fspath(out_dir))
        self.force = force
        self.progress = progress
        self.inputs = [str(i) for i in inputs]
        self.records: dict[int, dict] = {}
        self.info: dict[str, Any] = {"workers_lost": 0, "retries": 0, "worker_init_s": []}
        self.wall_s = 0.0
        self.interrupted = False

    # ---- the output folder --------------------------------------------------------------------------------
    def _prepare_output(self) -> list[_Task]:
        out = self.out_dir
        if out.exists() and not out.is_dir():
            raise BatchError(f"{out}: exists and is not a folder")
        out.mkdir(parents=True, exist_ok=True)
        self._made = (read_journal(out) or {}) if self.force else {}  # (the journal before a forced run redoes it)
        manifest = out / MANIFEST_NAME
        want = {"fingerprint": self.opts.fingerprint(), "options": self.opts.shaping()}
        if manifest.exists():
            try:
                have = json.loads(manifest.read_text())
            except (OSError, ValueError):
                have = {}
            same = have.get("fingerprint") == want["fingerprint"] or same_options(have.get("options"), want["options"])
            if not same:  # (--raster-opt given in another order are the same options)
                if not self.force:
                    old = have.get("options", {})
                    diff = ", ".join(f"{k} {old.get(k)!r} -> {v!r}" for k, v in want["options"].items()
                                     if old.get(k) != v) or "unreadable manifest"
                    raise BatchError(f"{out}: holds outputs made with other options ({diff}); use --force to redo "
                                     "them, or another output folder")
                forget_journal(out)  # its files have the old options: a partial forced run leaves none to skip
        ours = manifest.exists()  # a batch wrote here before: existing outputs are its finished models
        done = [] if self.force else [i for i in range(len(self.models)) if all((out / f).exists() for f in
                                                                                self._files(i))]
        journal = read_journal(out) if done else None  # (None: a folder of a batch from before the journal)
        foreign = done if not ours else [i for i in done if journal is not None and
                                         not unchanged(out, self._files(i), journal)]
        if foreign:
            why = (f"and {out} has no batch manifest ({MANIFEST_NAME}): not written by gpuslice batch" if not ours else
                   f"but {out}'s batch journal ({JOURNAL_NAME}) does not list it as it is: put there or changed since")
            raise BatchError(f"{out / self.models[foreign[0]].out}: exists, {why} ({len(foreign)} such outputs); use "
                             "--force to replace them, or another output folder")
        from ..io.atomic import atomic_write_text

        atomic_write_text(manifest, json.dumps(want, indent=1, sort_keys=True) + "\n")
        for i in done:
            if journal is None:  # taken as finished by the older rule: recorded now, so the next run knows them
                record_finished(out, self._files(i))
            self._finish(i, {"model": self.models[i].rel, "output": self.models[i].out, "status": "skipped",
                             "error": None}, None)
        return [_Task(i) for i in sorted(set(range(len(self.models))) - set(done))]

    def _record_committed(self, since_ns: int) -> None:
        """After Ctrl-C: journal the models without a result whose files a worker put in place during this run
        (:func:`.journal.record_written_since`): a re-run skips them (it refused them by name)."""
        for i in range(len(self.models)):
            if i not in self.records:
                record_written_since(self.out_dir, self._files(i), since_ns)

    def _cleanup_temporaries(self) -> None:
        """Remove temporaries left by killed workers beside this batch's outputs (``.NAME.tmp-…``): one listing
        per output folder, so 10,000 models in one folder cost one scan, not 10,000."""
        by_dir: dict[Path, set[str]] = collections.defaultdict(set)
        for m in self.models:
            target = self.out_dir / m.out
            by_dir[target.parent].add(target.name)
            if self.opts.check:
                by_dir[target.parent].add(check_path(target).name)
        for folder, names in by_dir.items():
            with contextlib.suppress(OSError):
                for entry in os.scandir(folder):
                    name = entry.name
                    k = name.find(".tmp-")
                    if name.startswith(".") and k > 1 and name[1:k] in names:
                        remove_path(Path(entry.path))

    def _files(self, index: int) -> list[str]:
        """The files model ``index`` leaves in the output folder (its output; with checks, its check report)."""
        out = self.models[index].out
        return [out, str(check_path(out))] if self.opts.check else [out]

    def _finish(self, index: int, rec: dict, task: _Task | None) -> None:
        m = self.models[index]
        if rec["status"] == "done":
            record_finished(self.out_dir, self._files(index))
        elif self.force:  # a redo that failed: its old files (a batch's, as journaled) would be skipped next time
            remove_journaled(self.out_dir, self._files(index), self._made)
        rec["input"] = m.src
        if task is not None:
            rec["attempts"] = task.attempt
            rec["workers"] = [*task.workers, rec.get("worker")]
            if task.errors and rec["status"] == "done":
                rec["earlier_errors"] = list(task.errors)
        self.records[index] = rec
        if self.progress is not None:
            self.progress(rec)

    def _outcome(self, task: _Task, rec: dict, worker: str, n_workers: int) -> _Task | None:
        """Record a task's result; returns the retry task for a first failure."""
        rec["worker"] = worker
        if rec.get("worker_init_s"):
            self.info["worker_init_s"].append(rec["worker_init_s"])
        final = rec.pop("deterministic", False)  # the file or the options at fault: the same on any worker
        if rec["status"] == "failed" and task.attempt == 1 and not final:
            self.info["retries"] += 1
            return _Task(task.index, 2, task.lost, worker if n_workers > 1 else None, [rec["error"]], [worker])
        self._finish(task.index, rec, task)
        return None

    def _lost(self, task: _Task, worker: str) -> _Task | None:
        task.lost += 1
        if task.lost >= MAX_LOST:
            m = self.models[task.index]
            self._finish(task.index, {"model": m.rel, "output": m.out, "status": "failed", "worker": worker,
                                      "error": f"{m.src}: its worker process died {task.lost} times while "
                                               "slicing it"}, task)
            return None
        return task

    # ---- in this process ---------------------------------------------------------------------------------
    def _run_serial(self, tasks: list[_Task]) -> None:
        queue = collections.deque(tasks)
        while queue:
            task = queue.popleft()
            rec = run_model(self.models[task.index], self.opts, str(self.out_dir))
            retry = self._outcome(task, rec, "main", 1)
            if retry is not None:
                queue.appendleft(retry)

    # ---- local worker processes --------------------------------------------------------------------------
    def _run_local(self, tasks: list[_Task], workers: int, threads: int) -> None:
        ctx = mp_context()
        # the whole environment: a forkserver started earlier carries the environment of that moment
        env = {**os.environ, **pocl_thread_env(threads)}
        init_args = (env, self.opts.params.device, self.opts.params.backend, self.opts.raster is not None,
                     os.getpid())

        def new_executor():
            return ProcessPoolExecutor(1, mp_context=ctx, initializer=init_worker, initargs=init_args)

        helpers_ignoring_sighup(ctx)
        slots = [Slot(f"local-{k}", new_executor()) for k in range(workers)]
        self._slots = slots
        queue: collections.deque[_Task] = collections.deque(tasks)
        out_root = str(self.out_dir)

        def take(slot: Slot) -> _Task | None:
            for k, t in enumerate(queue):
                if t.avoid != slot.name:
                    del queue[k]
                    return t
            return None

        try:
            while queue or any(s.inflight for s in slots):
                for depth in range(1, PREFETCH + 1):  # round-robin: every worker gets a task before any a second
                    for slot in slots:
                        if len(slot.inflight) >= depth or not queue:
                            continue
                        task = take(slot)
                        if task is None:
                            continue
                        try:
                            fut = slot.executor.submit(run_model, self.models[task.index], self.opts, out_root)
                        except BrokenProcessPool:
                            queue.appendleft(task)
                            continue
                        slot.inflight[fut] = task
                # a retry that avoids the one idle worker while the others are gone would wait forever
                if queue and not any(s.inflight for s in slots):
                    for t in queue:
                        t.avoid = None
                    continue
                every = [f for s in slots for f in s.inflight]
                done, _ = wait(every, timeout=0.5, return_when=FIRST_COMPLETED)
                for slot in slots:
                    finished = [f for f in slot.inflight if f in done]
                    broken = False
                    for fut in finished:
                        task = slot.inflight.pop(fut)
                        try:
                            rec = fut.result()
                        except (BrokenProcessPool, SystemExit):  # (a worker stopped by SIGTERM mid-model: lost)
                            broken = True
                            again = self._lost(task, slot.name)
                            if again is not None:
                                queue.appendleft(again)
                            continue
                        except Exception as exc:  # pickling trouble and the like: the model's failure
                            m = self.models[task.index]
                            rec = {"model": m.rel, "output": m.out, "status": "failed",
                                   "error": f"{m.src}: {one_line(exc)}"}
                        retry = self._outcome(task, rec, slot.name, workers)
                        if retry is not None:
                            queue.appendleft(retry)
                    if broken:
                        # the worker died: the rest of its tasks are lost too; replace it and re-run them
                        self.info["workers_lost"] += 1
                        for task in list(slot.inflight.values()):
                            again = self._lost(task, slot.name)
                            if again is not None:
                                queue.appendleft(again)
                        slot.inflight.clear()
                        slot.executor.shutdown(wait=False, cancel_futures=True)
                        slot.executor = new_executor()
        except BaseException:
            stop_slots(slots)
            raise
        for slot in slots:
            slot.executor.shutdown(wait=True)

    def worker_pids(self) -> list[int]:
        """PIDs of the local worker processes now running (for tests and monitoring)."""
        pids = []
        for slot in getattr(self, "_slots", []):
            procs = getattr(slot.executor, "_processes", None) or {}
            pids += [p.pid for p in procs.values() if p.is_alive()]
        return pids

    # ---- Dask --------------------------------------------------------------------------------------------
    def _run_dask(self, tasks: list[_Task], client, transfer: str) -> None:
        from distributed import as_completed

        plugin = _device_plugin(self.opts.params.device, self.opts.params.backend)
        client.register_plugin(plugin, name="gpuslice-device")
        n_workers = max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))
        window = 4 * n_workers  # bounded: 10,000 models never sit in the client's memory at once
        queue = collections.deque(tasks)
        by_future: dict[Any, _Task] = {}
        out_root = str(self.out_dir.resolve()) if transfer == "shared" else None
        ac = as_completed()

        def submit(task: _Task) -> None:
            m = self.models[task.index]
            data = Path(m.location).read_bytes() if transfer == "bytes" else None
            kwargs: dict[str, Any] = {}
            if task.avoid is not None:
                others = [w for w in client.scheduler_info(n_workers=-1)["workers"] if w != task.avoid]
                if others:
                    kwargs = {"workers": others, "allow_other_workers": True}
            fut = client.submit(run_model, m, self.opts, out_root, data, pure=False, retries=0,
                                key=f"gpuslice-{task.index}-{task.attempt}-{task.lost}-{os.getpid()}-{time.time_ns()}",
                                **kwargs)
            by_future[fut] = task
            ac.add(fut)

        try:
            while queue and len(by_future) < window:
                submit(queue.popleft())
            for fut in ac:
                task = by_future.pop(fut)
                m = self.models[task.index]
                try:
                    rec = fut.result()
                    worker = rec.get("worker") or f"{rec.get('host')}:{rec.get('pid')}"
                except Exception as exc:  # KilledWorker (the task killed its workers), a lost connection
                    rec = {"model": m.rel, "output": m.out, "status": "failed",
                           "error": f"{m.src}: {one_line(exc)}"}
                    worker = "?"
                fut.release()
                if rec["status"] == "done" and "check_payload" in rec:  # first: an output means a full model
                    atomic_write_tree(check_path(self.out_dir / m.out), rec.pop("check_payload"))
                if rec["status"] == "done" and "payload" in rec:
                    atomic_write_tree(self.out_dir / m.out, rec.pop("payload"))
                retry = self._outcome(task, rec, worker, n_workers)
                if retry is not None:
                    queue.appendleft(retry)
                while queue and len(by_future) < window:
                    submit(queue.popleft())
        except BaseException:
            for fut in list(by_future):
                fut.cancel()
            raise

    # ---- entry -------------------------------------------------------------------------------------------
    def run(self, workers: int | None = None, *, threads: int | None = None, client=None,
            transfer: str = "bytes") -> dict[str, Any]:
        """Run the batch and return its report.

        workers : local worker processes; 0 slices in this process; None: :func:`default_workers`.
        threads : PoCL threads per local worker (default: cores // workers).
        client : a ``distributed.Client``: run the tasks on its cluster instead (``workers`` is ignored).
        transfer : with a client, ``"bytes"`` (model bytes go to the workers and output bytes come back to this
            process, which writes them; the default) or ``"shared"`` (workers read the models and write the outputs
            by their absolute paths: a shared file system mounted alike everywhere).
        """
        if transfer not in ("shared", "bytes"):
            raise BatchError(f"unknown transfer '{transfer}' (use shared or bytes)")
        for name, v, least in (("workers", workers, 0), ("threads", threads, 1)):  # (-1, NaN, 1.5, True ran)
            whole = isinstance(v, numbers.Integral) and not isinstance(v, bool)
            if v is not None and not (whole and least <= v <= MAX_LOCAL):
                raise BatchError(f"{name} must be a whole number from {least} to {MAX_LOCAL}, got {v!r}")
        t0 = time.perf_counter()
        started_ns = time.time_ns()
        tasks = self._prepare_output()
        mode = "dask" if client is not None else "serial" if workers == 0 else "local"
        self.info.update(mode=mode, transfer=transfer if client is not None else "shared")
        try:
            if client is not None:
                self.info["scheduler"] = getattr(client.scheduler, "address", None)
                self.info["workers"] = len(client.scheduler_info(n_workers=-1).get("workers", {}))
                if tasks:
                    self._run_dask(tasks, client, transfer)
            elif workers == 0:
                self.info["workers"] = 0
                self._run_serial(tasks)
            else:
                auto_n, _ = default_workers(len(tasks), self.opts.params.device, self.opts.params.backend)
                n = auto_n if workers is None else max(1, workers)
                n = max(1, min(n, len(tasks))) if tasks else n
                t = threads or max(1, _cores() // n)
                self.info.update(workers=n, pocl_threads_per_worker=t)
                if tasks:
                    self._run_local(tasks, n, t)
        except KeyboardInterrupt:
            self.interrupted = True
            self._record_committed(started_ns)
            raise
        finally:
            self._cleanup_temporaries()
            self.wall_s = time.perf_counter() - t0
        return self.report()

    def report(self) -> dict[str, Any]:
        """The batch report: ``options``, ``models`` (one record per model, sorted by path; unfinished models
        have status ``"not run"`` after an interrupt) and ``summary`` (counts, wall time, models per second)."""
        records = []
        for i, m in enumerate(self.models):
            rec = self.records.get(i) or {"model": m.rel, "input": m.src, "output": m.out, "status": "not run",
                                          "error": None}
            records.append({k: v for k, v in rec.items() if k not in ("payload", "check_payload")})
        counts = collections.Counter(r["status"] for r in records)
        done = [r for r in records if r["status"] == "done"]
        info = dict(self.info)
        init = info.pop("worker_init_s")
        summary = {
            "models": len(records),
            "done": counts.get("done", 0),
            "skipped": counts.get("skipped", 0),
            "failed": counts.get("failed", 0),
            "not_run": counts.get("not run", 0),
            "interrupted": self.interrupted,
            "wall_s": self.wall_s,
            "models_per_s": len(done) / self.wall_s if self.wall_s > 0 else 0.0,
            "facets": sum(r.get("facets", 0) for r in done),
            "layers": sum(r.get("layers", 0) for r in done),
            "task_s": sum(r["timings_s"]["total"] for r in done if "timings_s" in r),
            **({"checks": checks_summary(done)} if self.opts.check else {}),
            "worker_init_s": init,
            **info,
        }
        return {
            "gpuslice_batch": 1,
            "inputs": self.inputs,
            "output_dir": str(self.out_dir),
            "options": self.opts.shaping() | {"backend": self.opts.params.backend, "device": self.opts.params.device},
            "fingerprint": self.opts.fingerprint(),
            "models": records,
            "summary": summary,
        }


def _device_plugin(device: str | None, backend: str):
    """A Dask worker plugin that makes the OpenCL device and builds the kernels once, when a worker starts or
    joins (defined here so that ``distributed`` is imported only for Dask batches; Dask pickles it by value)."""
    from distributed import WorkerPlugin

    class GpusliceDevicePlugin(WorkerPlugin):
        idempotent = True

        def setup(self, worker) -> None:
            if backend == "opencl":
                with contextlib.suppress(Exception):  # reported by the first task instead
                    _worker_device(device)

    return GpusliceDevicePlugin()


def run_batch(inputs: Sequence[str | os.PathLike], out_dir: str | os.PathLike, opts: BatchOptions | None = None, *,
              glob: str | None = None, workers: int | None = None, client=None, transfer: str = "bytes",
              force: bool = False, progress: Callable[[dict], None] | None = None) -> dict[str, Any]:
    """Slice every model found in ``inputs`` into ``out_dir`` (mirroring the input tree); returns the report.

    See :func:`discover` for ``inputs`` and ``glob``, :meth:`BatchRunner.run` for ``workers``, ``client`` and
    ``transfer``. A model whose output exists is skipped unless ``force``.
    """
    opts = opts or BatchOptions()
    models = discover(inputs, glob, opts.suffix, out_dir)
    runner = BatchRunner(models, opts, out_dir, force=force, progress=progress, inputs=[str(i) for i in inputs])
    return runner.run(workers, client=client, transfer=transfer)
