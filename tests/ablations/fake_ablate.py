"""Stand-ins for ``python -m ablations ablate`` that an ``ablate-sweep`` worker starts (the ``program`` seam of
``ablations.sweep.run_sweep``). Run by path, with ablate's arguments after the stand-in's own::

    python fake_ablate.py kill-worker-once SWEEP_DIR RUN_ID[,RUN_ID...] -- ABLATE_ARGS...
        The real ablate, except that a named run (or population: its job id), the first time it writes a checkpoint
        (every member has, in a population), waits until that checkpoint has reached the sweep folder, notes it in
        SWEEP_DIR/.killed/<run_id> and SIGKILLs the Ray worker that started it (as a node's out-of-memory killer
        would); the worker's death takes this process with it. A run with a note runs as ablate does: the retry,
        and any later sweep in the same folder.

    python fake_ablate.py signal-once SWEEP_DIR RUN_ID[,RUN_ID...] -- ABLATE_ARGS...
        The real ablate, except that a named run, right after its first checkpoint, sends itself SIGTERM (as a job
        scheduler draining a node would) and notes the checkpoint in SWEEP_DIR/.signalled/<run_id>: ablate stops
        as it does on a signal (summary "interrupted", exit status 130). A run with a note runs as ablate does.

    python fake_ablate.py record LOG SECONDS -- ABLATE_ARGS...
        No training: spends SECONDS writing --iters iterations (a metrics line and a small checkpoint each, which
        the worker ships to the driver as it does a real run's), then a summary, and appends {"run", "pid",
        "start", "end", "threads", "members", "cuda_visible_devices"} (time.time() seconds; its --threads; its
        --member values; the GPUs it was given) to LOG, to measure how many runs overlap and where they ran.
        With --member: a population folder (population.json) holding a run folder per member, named as ablate
        names them; --resume continues from the newest checkpoint every run folder has (its metrics cut there),
        so an attempt that repeats or skips an iteration shows in the metrics. It checkpoints every
        --checkpoint-every iterations (default 1) and the last, and stops on SIGINT as ablate does: the first lets
        the iteration finish and checkpoints it, a second stops at once and checkpoints the last finished one;
        either way the summary says "interrupted", the log line gives "interrupted" (the iteration kept) and the
        exit status is 130.
"""

from __future__ import annotations

import json
import os
import runpy
import signal
import sys
import time
from pathlib import Path

from ablations.run_folder import POPULATION_RECORD

#: Seconds a run waits for the sweep folder to receive its checkpoint before it gives up killing its worker.
WAIT_FOR_STORE_S = 120.0
#: A population folder's record.
POPULATION = POPULATION_RECORD


def _value(args: list[str], flag: str) -> str | None:
    return args[args.index(flag) + 1] if flag in args else None


def run_id_of(args: list[str]) -> str:
    """The run an ablate command line is about: its --name, or the folder it resumes."""
    return _value(args, "--name") or Path(_value(args, "--resume")).name


def ablate_acting_once(sweep: Path, notes: str, victims: set[str], args: list[str], act) -> None:
    """The real ablate; a named run without a note in ``sweep/notes/`` calls ``act(checkpoint, note, run_id)``
    right after writing its first checkpoint."""
    run_id = run_id_of(args)
    note = sweep / notes / run_id
    if run_id in victims and not note.exists():
        # Patched before ablations is imported (the run folder module looks it up when it saves).
        import gradlab.checkpoint

        save = gradlab.checkpoint.save_checkpoint

        def save_then_act(path, state):
            save(path, state)
            if not note.exists() and every_member_has(Path(path)):
                note.parent.mkdir(parents=True, exist_ok=True)
                act(Path(path), note, run_id)

        gradlab.checkpoint.save_checkpoint = save_then_act
    sys.argv = [sys.argv[0], "ablate", *args]
    runpy.run_module("ablations", run_name="__main__", alter_sys=True)


def every_member_has(checkpoint: Path) -> bool:
    """Whether every member of the population whose run folder holds ``checkpoint`` has one of its iteration (a
    population checkpoints its members one after the other); True for a run alone."""
    home = checkpoint.parent.parent.parent
    if not (home / POPULATION).is_file():
        return True
    names = json.loads((home / POPULATION).read_text())["members"]
    return all((home / name / "checkpoints" / checkpoint.name).exists() for name in names)


def kill_worker(sweep: Path):
    def act(checkpoint: Path, note: Path, run_id: str) -> None:
        # the attempt runs in its scratch folder, where the job's folder is the one the sweep keeps under runs/
        shipped = sweep / "runs" / os.path.relpath(checkpoint)
        deadline = time.monotonic() + WAIT_FOR_STORE_S
        while not shipped.exists():
            if time.monotonic() > deadline:
                return  # the test sees no kill and fails on the attempt count
            time.sleep(0.05)
        note.write_text(checkpoint.name)
        os.kill(os.getppid(), signal.SIGKILL)
        signal.pause()  # until PR_SET_PDEATHSIG (ablations/sweep/child.py) ends this process

    return act


def signal_self(checkpoint: Path, note: Path, run_id: str) -> None:
    note.write_text(checkpoint.name)
    os.kill(os.getpid(), signal.SIGTERM)


def member_folders(args: list[str]) -> list[str]:
    """The run folders ablate makes of an ablate command line with --member (its own parser and names)."""
    from ablations.cli import parse
    from ablations.population import AblateConfig, member_name

    members = parse(AblateConfig, args).members()
    return [member_name(m, members) for m in members]


def record(log: Path, seconds: float, args: list[str]) -> None:
    start = time.time()
    run_id = run_id_of(args)
    iters = int(_value(args, "--iters") or 1)
    home = Path(_value(args, "--out") or ".") / run_id
    resume = _value(args, "--resume")
    if resume is not None:
        home = Path(resume)
        population = json.loads((home / POPULATION).read_text()) if (home / POPULATION).is_file() else None
        names = population["members"] if population else [""]
        iters = json.loads((home / names[0] / "config.json").read_text())["config"]["iters"]
    else:
        names = member_folders(args) if "--member" in args else [""]
        home.mkdir(parents=True)
        if names != [""]:
            (home / POPULATION).write_text(json.dumps({"members": names, "command": ["fake_ablate.py", *args]}))
    runs = [home / name for name in names]
    every = int(_value(args, "--checkpoint-every") or 1)
    sigints = []
    signal.signal(signal.SIGINT, lambda *_: sigints.append(1))
    done = 0
    for run in runs:
        (run / "checkpoints").mkdir(parents=True, exist_ok=True)
        if resume is None:
            (run / "config.json").write_text(json.dumps({"config": {"iters": iters},
                                                         "command": ["fake_ablate.py", *args]}))
    if resume is not None:  # from the newest iteration every run folder has a checkpoint of, its metrics cut there
        have = [{int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("ckpt_*.pt")} for run in runs]
        done = max(set.intersection(*have), default=0)
        for run in runs:
            lines = (run / "metrics.jsonl").read_text().splitlines()
            kept = [line for line in lines if json.loads(line)["iter"] <= done]
            (run / "metrics.jsonl").write_text("".join(line + "\n" for line in kept))
    stopped = None
    for it in range(done + 1, iters + 1):
        end = time.monotonic() + seconds / iters
        while time.monotonic() < end and len(sigints) < 2:
            time.sleep(0.02)
        if len(sigints) >= 2:  # stopped at once: this iteration is lost
            stopped = it - 1
            break
        for run in runs:
            with open(run / "metrics.jsonl", "a") as metrics:
                metrics.write(json.dumps({"iter": it, "return_mean": float(it), "pid": os.getpid()}) + "\n")
        if sigints or it % every == 0 or it == iters:
            for run in runs:
                (run / "checkpoints" / f"ckpt_{it:06d}.pt").write_bytes(b"fake state %d" % it)
        if sigints:
            stopped = it
            break
    if stopped is not None:
        for run in runs:
            if stopped and not (run / "checkpoints" / f"ckpt_{stopped:06d}.pt").exists():
                (run / "checkpoints" / f"ckpt_{stopped:06d}.pt").write_bytes(b"fake state %d" % stopped)
            (run / "summary.json").write_text(json.dumps({"status": "interrupted", "iterations": stopped,
                                                          "error": f"SIGINT after iteration {stopped}"}))
    else:
        for run in runs:
            (run / "summary.json").write_text(json.dumps({"status": "finished", "iterations": iters,
                                                          "final_return": float(iters)}))
    line = json.dumps({"run": run_id, "pid": os.getpid(), "start": start, "end": time.time(),
                       "interrupted": stopped,
                       "threads": _value(args, "--threads"), "members": names, "resumed_from": done,
                       "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES")}) + "\n"
    with open(log, "a") as f:  # one short append per run: lines of concurrent runs do not interleave
        f.write(line)
    if stopped is not None:
        raise SystemExit(130)


def main() -> None:
    split = sys.argv.index("--")
    own, args = sys.argv[1:split], sys.argv[split + 1:]
    if own[0] == "kill-worker-once":
        ablate_acting_once(Path(own[1]), ".killed", set(own[2].split(",")), args, kill_worker(Path(own[1])))
    elif own[0] == "signal-once":
        ablate_acting_once(Path(own[1]), ".signalled", set(own[2].split(",")), args, signal_self)
    elif own[0] == "record":
        record(Path(own[1]), float(own[2]), args)
    else:
        sys.exit(f"fake_ablate.py: unknown stand-in {own[0]!r}")


if __name__ == "__main__":
    main()
