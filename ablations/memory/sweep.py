"""The sweep driver: one worker process per point, timeouts, failure classification, resume."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from ablations.memory.config import MemoryConfig, point_id
from ablations.memory.plots import plot_sweep
from ablations.memory.table import (
    COLUMNS,
    FINAL_STATUSES,
    FIXED,
    TIMED_COLUMNS,
    check_compatible,
    now,
    point_key,
    read_csv,
    write_results,
)
from ablations.memory.worker import DEFAULT_MEASURE, OOM_PATTERNS, read_result

__all__ = ["sweep", "run_point"]


def _tail(path: Path, n: int = 40) -> list[str]:
    try:
        return [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()][-n:]
    except OSError:
        return []


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def _classify_exit(rc: int | None, log_path: Path, rel_log: str) -> tuple[str, str]:
    """(status, error) of a worker that ended without writing an outcome (crashed, killed, exited early)."""
    if rc in (-signal.SIGKILL, 128 + signal.SIGKILL):
        return "oom", f"worker killed by SIGKILL (most likely the kernel's out-of-memory killer); see {rel_log}"
    tail = _tail(log_path)
    if rc is not None and rc < 0:
        name = signal.Signals(-rc).name if -rc in signal.valid_signals() else str(-rc)
        why = f"worker died from signal {name}"
    elif rc == 0:
        why = "worker exited without a result"
    else:
        why = f"worker exited with code {rc}"
    status = "oom" if any(p in ln.lower() for ln in tail for p in OOM_PATTERNS) else "error"
    last = next((ln for ln in reversed(tail) if not ln.startswith("#")), "")
    return status, (f"{why}: {last}"[:500] if last else why)


def run_point(point: dict, *, out: Path, timeout_s: float, measure: str = DEFAULT_MEASURE,
              running: set | None = None) -> dict:
    """Run one point in a fresh process and return its CSV row (never raises for a failed point).

    Classification: ``ok``; ``oom`` for torch.OutOfMemoryError / MemoryError / an allocator failure in the
    worker, a worker killed by SIGKILL (exit -9 or 137: the kernel's out-of-memory killer), or a non-zero exit
    whose log reports running out of memory; ``timeout`` past ``timeout_s``; ``error`` (with the message)
    otherwise. The worker's stdout and stderr go to ``out/logs/<point>.log``. ``running``: a set the worker's
    process is kept in while it runs (so that another thread can kill it).
    """
    pid = point_id(point)
    log_path = out / "logs" / f"{pid}.log"
    result_path = out / ".points" / f"{pid}.jsonl"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    result_path.parent.mkdir(parents=True, exist_ok=True)
    result_path.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "ablations.memory", "--point", json.dumps(point), "--result", str(result_path)]
    if measure != DEFAULT_MEASURE:
        cmd += ["--measure", measure]
    started, t0 = now(), time.perf_counter()
    status = error = None
    with open(log_path, "w") as log:
        log.write(f"# {started} {' '.join(cmd)}\n")
        log.flush()
        # A new session (process group): a timeout or Ctrl-C kills the worker AND anything it spawned
        # (compile workers), and the terminal's SIGINT reaches only the sweep, which then cleans up.
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
        if running is not None:
            running.add(proc)
        try:
            rc = proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _kill_group(proc)
            rc, status, error = proc.returncode, "timeout", f"no result after {timeout_s:g} s; killed"
        except BaseException:
            _kill_group(proc)
            raise
        finally:
            if running is not None:
                running.discard(proc)
    point_s = time.perf_counter() - t0
    result = read_result(result_path)
    result_path.unlink(missing_ok=True)
    rel_log = str(log_path.relative_to(out))
    if status is None:
        if result.get("status") in ("ok", "oom", "error") and rc == 0:
            status, error = result["status"], result.get("error")
        else:
            status, error = _classify_exit(rc, log_path, rel_log)
    row = {k: point.get(k) for k in COLUMNS}
    row.update({k: v for k, v in result.items() if k in COLUMNS and k not in FIXED and k not in ("mode",)})
    for k in ("meshes", "verts_per_mesh"):
        row[k] = point[k]
    row.update(status=status, error=error, started=started, point_s=point_s, log=rel_log)
    if status != "ok":
        for k in TIMED_COLUMNS:
            row[k] = None
    row["_environment"] = result.get("environment")
    return row


def sweep(cfg: MemoryConfig, *, measure: str = DEFAULT_MEASURE) -> list[dict]:
    """Run (or continue) the sweep; returns all rows of memory.csv. Raises ValueError on bad input."""
    from tqdm.auto import tqdm

    from gradlab.seeding import resolve_device

    cfg.validate()
    device = str(resolve_device(cfg.device))
    out = Path(cfg.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"output folder {out} is not writable: {e}") from None

    points = cfg.points(device)
    csv_path, json_path = out / "memory.csv", out / "memory.json"
    rows = read_csv(csv_path) if csv_path.exists() else []
    check_compatible(rows, points, csv_path)
    meta: dict = {}
    if json_path.exists():
        try:
            meta = {k: v for k, v in json.loads(json_path.read_text()).items() if k != "rows"}
        except (OSError, json.JSONDecodeError):
            meta = {}
    meta.setdefault("started", now())
    meta["config"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()}
    meta.setdefault("commands", []).append({"argv": sys.argv, "cwd": os.getcwd(), "started": now()})

    keep = set(FINAL_STATUSES) if cfg.retry_failed else None
    done = {point_key(r) for r in rows if keep is None or r["status"] in keep}
    todo = [p for p in points if point_key(p) not in done]
    bar = tqdm(total=len(points), initial=len(points) - len(todo), disable=not cfg.progress, unit="point",
               desc=f"memory {cfg.task}", dynamic_ncols=True)
    def record(p: dict, row: dict) -> None:
        nonlocal rows
        env = row.pop("_environment", None)
        if env and "environment" not in meta:
            meta["environment"] = env
        rows = [r for r in rows if point_key(r) != point_key(p)] + [row]
        write_results(out, rows, meta)
        bwd = row.get("bwd_ms")
        bar.set_postfix(status=row["status"], bwd_ms="-" if bwd is None else f"{bwd:.0f}")
        bar.update(1)

    running: set = set()
    try:
        write_results(out, rows, meta)
        if cfg.jobs == 1:
            for p in todo:
                bar.set_description(point_id(p))
                record(p, run_point(p, out=out, timeout_s=cfg.timeout_s, measure=measure))
        else:
            bar.set_description(f"memory {cfg.task}, {cfg.jobs} points at once")
            with concurrent.futures.ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
                futures = {pool.submit(run_point, p, out=out, timeout_s=cfg.timeout_s, measure=measure,
                                       running=running): p for p in todo}
                try:
                    # rows are recorded (and the files written) by this thread alone, as points finish
                    for future in concurrent.futures.as_completed(futures):
                        record(futures[future], future.result())
                except BaseException:  # Ctrl-C or a failed write: no worker outlives the sweep
                    for future in futures:
                        future.cancel()
                    for proc in list(running):
                        _kill_group(proc)
                    raise
    finally:
        bar.close()
    rows = read_csv(csv_path)  # exactly what is on disk (numbers as the CSV stores them)
    plot_sweep(rows, out)
    return rows
