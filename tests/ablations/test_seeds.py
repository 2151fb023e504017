"""ablations.reports.arms and .seeds: arms named from run folders, iteration times measured alone, the seed-statistics
section with its verdict, and the probe statistics over looking probes, on synthetic runs whose answers are known."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ablations.reports import arms, load_floors, seeds
from ablations.run_folder import Run, find_runs, load_run

#: Few bootstrap resamples keep these tests fast; the intervals they check are far from their bounds.
REPS = 20


def write_run(parent, name, *, task="hopper", mode="decoupled", seed=0, raster="softmax", preset="dva",
              overridden=None, settings=None, evals=(), every=10, iters=None, iter_ms=50.0, members=None,
              probes=None, device="GPU-A"):
    """A run folder as `ablate` writes one. config.json: the preset's record (raster model, learning-rate decay
    and environments supplied unless ``overridden`` names them: {key: (flag, preset's value)}), the population
    record when ``members`` is given; metrics.jsonl: every iteration with ``iter_ms`` and ``action_std``, the evaluation
    returns ``evals`` at iterations every, 2 every, ..., ``probes`` {iter: (sensitivity per frame, more keys)}."""
    overridden = overridden or {}
    decay = 2000 if preset == "shac-diffrender" else 30000
    config = {"task": task, "mode": mode, "seed": seed, "raster_model": raster, "preset": preset,
              "lr_decay_iters": decay, "num_envs": 64, "horizon": 32, "image_size": 84, "compile": True,
              "encoder_lr_scale": 1.0, "warmup_iters": 2, "eval_every": every, "name": name, "out": str(parent),
              **{k: v[0] for k, v in overridden.items()}, **(settings or {})}
    supplied = {k: v for k, v in (("raster_model", raster), ("lr_decay_iters", decay), ("num_envs", config["num_envs"]))
                if k not in overridden}
    record = {"config": config, "environment": {"device": "cuda", "gpu": device},
              "preset": {"name": preset, "supplied": supplied,
                         "overridden": {k: {"flag": f, "preset": p} for k, (f, p) in overridden.items()}}}
    if members:
        record["population"] = {"folder": parent.name, "index": 0, "members": members}
    run = parent / name
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps(record))
    at = {every * (i + 1): r for i, r in enumerate(evals)}
    probes = probes or {}
    last = iters or max([*at, *probes, 1])
    lines = []
    for it in range(1, last + 1):
        m = {"iter": it, "wall_s": 0.1 * it, "return_mean": 1.0, "iter_ms": iter_ms, "action_std": 0.4,
             "probed": it in probes}
        if it in at:
            m.update(eval_return_mean=at[it], eval_return_std=1.0, eval_length_mean=100.0)
        if it in probes:
            frames, more = probes[it]
            m.update({f"image_sensitivity_f{i}": v for i, v in enumerate(frames)}, **more)
        lines.append(json.dumps(m))
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    return run


# ---------------------------------------------------------------------------------------------------- arms
def test_arms_are_named_like_ablate_papers(tmp_path):
    for task in ("hopper", "ant"):
        p = tmp_path / task
        write_run(p, "dec", task=task)
        write_run(p, "dec_other_folder", task=task, seed=1, settings={"eval_every": 50, "device": "cpu"})
        write_run(p, "soft", task=task, mode="full")
        write_run(p, "hard", task=task, mode="full", raster="hard", preset="shac-diffrender")
        write_run(p, "hard_dva", task=task, mode="full", overridden={"raster_model": ("hard", "softmax")})
        write_run(p, "alpha", task=task, mode="full", overridden={"raster_model": ("alpha", "softmax")})
        write_run(p, "blind", task=task, mode="blind")
        write_run(p, "state", task=task, mode="state", raster=None)
        write_run(p, "dec_hard", task=task, overridden={"raster_model": ("hard", "softmax")})
        write_run(p, "dec_encoder", task=task, settings={"encoder_lr_scale": 0.1})
        write_run(p, "dec_decay", task=task, overridden={"lr_decay_iters": (2000, 30000)})
        write_run(p, "dec_decay_as_preset", task=task, seed=2, overridden={"lr_decay_iters": (30000, 30000)})
    runs = find_runs([tmp_path / "hopper", tmp_path / "ant"])
    names = {(r.task, r.path.name): n for r, n in zip(runs, arms.arm_names(runs).values())}
    assert set(names.values()) == {"decoupled", "full-soft", "full-hard", "full-hard-dva", "full-alpha", "blind",
                                   "state", "decoupled (hard)", "decoupled (encoder_lr_scale=0.1)",
                                   "decoupled (lr_decay_iters=2000)"}
    for task in ("hopper", "ant"):  # the same arms on both tasks, although the presets' values differ per task
        assert names[(task, "dec")] == names[(task, "dec_other_folder")] == "decoupled"
        assert names[(task, "dec_decay_as_preset")] == "decoupled"  # a flag at the preset's own value
        assert names[(task, "hard")] == "full-hard" and names[(task, "hard_dva")] == "full-hard-dva"
    label = arms.arm_label(runs)
    order = [label(r) for r in arms.in_arm_order([r for r in runs if r.task == "hopper"], label)]
    assert order[:8] == ["decoupled"] * 3 + ["full-soft", "full-hard", "full-hard-dva", "full-alpha", "state"]
    assert order[8] == "blind"


# ---------------------------------------------------------------------------------------- iteration times
def _two_arms(parent, *, members=None, dec_ms=40.0, full_ms=100.0, device="GPU-A"):
    for s in (0, 1):
        write_run(parent, f"dec{s}", seed=s, evals=[1.0], iter_ms=dec_ms, members=members, iters=20, device=device)
        write_run(parent, f"full{s}", seed=s, mode="full", evals=[1.0], iter_ms=full_ms, members=members, iters=20)
    runs = find_runs([parent])
    return runs, arms.arm_label(runs)


def test_iteration_times_of_single_runs_come_from_the_runs(tmp_path):
    runs, label = _two_arms(tmp_path / "runs")
    t = arms.iteration_times(runs, label)["hopper"]
    assert t.ms == {"decoupled": 40.0, "full-soft": 100.0}
    assert t.found["decoupled"].source == "runs" and t.found["decoupled"].n == 2 and "GPU-A" in t.why


def test_population_members_need_a_benchmark(tmp_path):
    runs, label = _two_arms(tmp_path / "pop", members=["a", "b", "c", "d"])
    t = arms.iteration_times(runs, label)["hopper"]
    assert t.ms is None and "population members" in t.why and "decoupled, full-soft" in t.why
    # benchmarks/iteration.py rows: the compiled rows of the runs' setting are the arms' times
    bench = tmp_path / "iteration.json"
    rows = [{"task": "hopper", "mode": "decoupled", "raster_model": "softmax", "iter_ms": 90.0, "bwd_ms": 40.0,
             "num_envs": 64, "horizon": 32, "image_size": 84, "compile": True},
            {"task": "hopper", "mode": "full", "raster_model": "softmax", "iter_ms": 115.0, "bwd_ms": 60.0,
             "num_envs": 64, "horizon": 32, "image_size": 84, "compile": True},
            {"task": "hopper", "mode": "full", "raster_model": "softmax", "iter_ms": 900.0, "bwd_ms": 60.0,
             "num_envs": 64, "horizon": 32, "image_size": 84, "compile": False},  # eager: another setting
            {"task": "hopper", "mode": "full", "raster_model": "hard", "iter_ms": 700.0, "bwd_ms": 60.0},
            {"task": "hopper", "mode": "full", "status": "oom", "iter_ms": None, "bwd_ms": None}]
    bench.write_text(json.dumps({"gpu": "GPU-B", "results": rows}))
    t = arms.iteration_times(runs, label, [bench])["hopper"]
    assert t.ms == {"decoupled": 90.0, "full-soft": 115.0} and "iteration.json on GPU-B" in t.why
    # benchmarks/population.py: only its population of one, a decoupled run alone, counts
    pop = tmp_path / "population.json"
    pop.write_text(json.dumps({"device": "cuda", "gpu": "GPU-B", "command": "population.py --num-envs 64 --horizon 32",
                               "rows": [
        {"kind": "population", "task": "hopper", "members": 12, "status": "ok", "iter_ms": 700.0},
        {"kind": "population", "task": "hopper", "members": 1, "status": "ok", "iter_ms": 93.0},
        {"kind": "separate", "task": "hopper", "members": 1, "arm": 1, "processes": 4, "status": "ok",
         "iter_ms": 300.0}]}))
    assert arms.benchmark_iteration_rows(pop) == ("GPU-B", [
        {"task": "hopper", "mode": "decoupled", "raster_model": "softmax", "iter_ms": 93.0, "compile": True,
         "num_envs": 64, "horizon": 32}])  # the sizes its command gave
    t = arms.iteration_times(runs, label, [pop])["hopper"]
    assert t.ms is None and t.found["decoupled"].ms == 93.0 and "full-soft: trained as population members" in t.why
    t = arms.iteration_times(runs, label, [pop, bench])["hopper"]  # the first file with a matching row wins
    assert t.found["decoupled"].ms == 93.0 and t.ms == {"decoupled": 93.0, "full-soft": 115.0}


def test_times_measured_on_different_devices_are_not_set_side_by_side(tmp_path):
    runs, label = _two_arms(tmp_path / "runs", device="GPU-X")  # decoupled on GPU-X, full on GPU-A
    t = arms.iteration_times(runs, label)["hopper"]
    assert t.ms is None and "different devices (GPU-A, GPU-X)" in t.why


# ------------------------------------------------------------------------------------------- the section
def _task(parent, task, dec, blind, **others):
    """Arms of one task whose final returns (their one evaluation each) are the given per-seed values; single
    runs, decoupled at 40 ms per iteration, the others at 80 ms."""
    arms = {"decoupled": ("decoupled", {}), "blind": ("blind", {}), "full-soft": ("full", {}),
            "full-hard-dva": ("full", {"overridden": {"raster_model": ("hard", "softmax")}})}
    for arm, finals in {"decoupled": dec, "blind": blind, **others}.items():
        mode, kw = arms[arm]
        for s, f in enumerate(finals):
            write_run(parent, f"{task}_{arm}_{s}", task=task, mode=mode, seed=s, evals=[f],
                      iter_ms=40.0 if arm == "decoupled" else 80.0, iters=10, **kw)


#: Ten seeds: the smallest sign-flip p-value is 2 / 2^10, so a difference every seed agrees on survives Holm's
#: correction over up to 25 comparisons (fewer seeds cannot: 5 give 0.0625 even alone).
DEC = [1000.0 + 50.0 * i for i in range(10)]
E3 = [5.0, -5.0, 0.0, 2.0, -2.0, 1.0, -1.0, 3.0, -3.0, 4.0]


def test_the_section_reads_arms_only_where_decoupled_beats_blind(tmp_path):
    parent = tmp_path / "runs"
    dec = DEC
    # hopper: decoupled beats blind by ~800 on every seed; full-soft ~+300, full-hard-dva ~-400
    _task(parent, "hopper", dec, [d - 800.0 + e for d, e in zip(dec, E3)],
          **{"full-soft": [d + 300.0 + e for d, e in zip(dec, E3[::-1])],
             "full-hard-dva": [d - 400.0 + e for d, e in zip(dec, E3)]})
    # ant: blind as good as decoupled on some seeds: no arm is read, however far full-soft is ahead
    _task(parent, "ant", dec, [d + (300.0 if i % 2 else -400.0) for i, d in enumerate(dec)],
          **{"full-soft": [d + 3000.0 for d in dec]})
    # cartpole: decoupled far above blind, but doing nothing scores high: it ranks no arms
    _task(parent, "cartpole", dec, [float(i) for i in range(10)], **{"full-soft": [d + 100.0 for d in dec]})
    runs = find_runs([parent])
    floors = load_floors()
    out = seeds.seed_statistics(runs, floors=floors, reps=REPS)
    hopper = out["hopper"].verdicts["equal iterations"]
    assert hopper.ranks and hopper.readings == {"full-soft": "better", "full-hard-dva": "worse"}
    ant = out["ant"].verdicts["equal iterations"]
    assert not ant.ranks and ant.readings == {} and "cannot be ranked on this task yet" in ant.reason
    cart = out["cartpole"].verdicts["equal iterations"]
    zero = floors.of("cartpole")["zero"]["mean"]
    assert not cart.ranks and cart.gate is None and f"zero action {zero:.0f}, floors.json" in cart.reason
    # all single runs, one device: the equal-wall-clock view exists (decoupled 40 ms, the others 80 ms: the
    # budget is 10 x 40 ms, five iterations of the others, before their evaluation at 10)
    ts = out["hopper"].stats
    assert ts.iter_ms_alone == {"decoupled": 40.0, "blind": 80.0, "full-soft": 80.0, "full-hard-dva": 80.0}
    assert ts.wall_s == pytest.approx(0.4) and ts.iters_at_wall["full-soft"] == 5
    assert ts.equal_wall.arms["full-soft"].final == {} and "equal wall-clock" in out["hopper"].verdicts

    text = "\n".join(seeds.seed_section(runs, tmp_path / "figs", tmp_path, floors=floors, reps=REPS, computed=out))
    assert "**Verdict (equal iterations, 10):** decoupled beats blind" in text
    assert ("full-soft: better than decoupled (differs after Holm correction); full-hard-dva: worse than decoupled "
            "(differs after Holm correction)") in text
    # the family: every paired comparison with a p-value, every task and view (equal wall-clock: full-soft and
    # full-hard-dva have no evaluation by 0.4 s on the hopper, nor full-soft on ant and cartpole)
    assert "the family of all 7 paired comparisons of this section" in text
    assert "10 of 10 seeds agree in sign, sign-flip p = 0.00195, Holm-adjusted p = 0.0137 (7 comparisons)" in text
    parts = dict(part.split("\n", 1) for part in text.split("\n### ")[1:])
    assert list(parts) == ["cartpole", "hopper", "ant"]  # tasks.TASKS' order
    ant_part = parts["ant"]
    assert "the pixel arms cannot be ranked on this task yet" in ant_part and "better than" not in ant_part
    assert ant_part.count("cannot be ranked yet |") == 1  # full-soft's reading in the table
    assert "D.Va's cartpole (with springs) ranks no arms" in text
    row = next(ln for ln in parts["hopper"].splitlines() if ln.startswith("| full-soft | 10 | 10 |"))
    assert "| 1 | 10 |" in row and "s0: 1304, s1: 1347," in row and "better than decoupled" in row
    assert "| 10 of 10 | 300.4 [" in row and "| 0.00195 | 0.0137 |" in row
    assert "evaluations at iterations 10." in parts["hopper"]  # the window every run's final return averages
    for name in ("difference_vs_budget_hopper.png", "learning_curves_hopper.png"):
        assert (tmp_path / "figs" / name).read_bytes()[:4] == b"\x89PNG" and f"](figs/{name})" in text
    assert (tmp_path / "figs" / "performance_profile_hopper.png").read_bytes()[:4] == b"\x89PNG"
    assert "](figs/performance_profile_hopper.png)" in text
    assert parts["hopper"].count("Swings of the training return up to iteration 10") == 1
    assert "| arm | training-return collapse rate: mean | per seed |" in parts["hopper"]
    assert "| decoupled | 0.00 | s0: 0.00, s1: 0.00, s2: 0.00, s3: 0.00," in parts["hopper"]  # a flat training return


def test_runs_without_evaluations_are_said_to_have_none(tmp_path):
    write_run(tmp_path / "runs", "old", iters=5)
    runs = find_runs([tmp_path / "runs"])
    text = "\n".join(seeds.seed_section(runs, tmp_path, tmp_path, reps=REPS))
    assert "No run logged a deterministic evaluation" in text and "--eval-every" in text


def test_two_runs_of_one_arm_and_seed_are_named_not_fatal(tmp_path):
    write_run(tmp_path / "runs", "a", evals=[1.0])
    write_run(tmp_path / "runs", "b", evals=[2.0])
    text = "\n".join(seeds.seed_section(find_runs([tmp_path / "runs"]), tmp_path, tmp_path, reps=REPS))
    assert "Not computed: arm 'decoupled' has two runs of task 'hopper' with seed 0" in text
    run = write_run(tmp_path / "other", "no_seed", task="ant", evals=[1.0])
    record = json.loads((run / "config.json").read_text())
    del record["config"]["seed"]
    (run / "config.json").write_text(json.dumps(record))
    text = "\n".join(seeds.seed_section([load_run(run)], tmp_path, tmp_path, reps=REPS))
    assert "### ant" in text and "config.json's config has no 'seed'" in text


# ---------------------------------------------------------------------------------------------- probes
def _probes(values):
    """Probes every 10 iterations: (total sensitivity over three frames, cos_full_decoupled, more keys)."""
    return {10 * (i + 1): ([s / 3] * 3, {"cos_full_decoupled": c, "grad_norm_render_term": 2.0 * c, **more})
            for i, (s, c, more) in enumerate(values)}


def test_probe_statistics_count_and_pool_the_looking_probes(tmp_path):
    parent = tmp_path / "runs"
    hs = {"grad_norm_full_hard": 1.0, "grad_norm_full_soft": 4.0, "cos_hard_soft": 0.5}
    # seed 0: first probe 6.0, so the bar is 0.6: probes 2 (0.01) and 4 (0.3) do not look, 1, 3, 5 do
    write_run(parent, "full0", mode="full", seed=0, probes=_probes(
        [(6.0, 0.9, hs), (0.01, 0.99, hs), (3.0, 0.2, hs), (0.3, 0.98, hs), (1.0, 0.4, hs)]))
    # seed 1: first probe 1.0, bar 0.1: all but the second look
    write_run(parent, "full1", mode="full", seed=1, probes=_probes(
        [(1.0, 0.8, hs), (0.05, 0.97, hs), (0.5, 0.1, {**hs, "grad_norm_full_soft": 2.0})]))
    write_run(parent, "blind0", mode="blind", seed=0, iters=50)  # no probes: no row
    runs = find_runs([parent])
    (p,) = seeds.arm_probes(runs)
    assert (p.task, p.arm) == ("hopper", "full-soft")
    assert p.looking == {0: 3, 1: 2} and p.probes == {0: 5, 1: 3}
    # pooled over seeds: cos 0.9, 0.2, 0.4 and 0.8, 0.1; over every probe the blind-phase ones join them
    assert p.medians["cos_full_decoupled"] == pytest.approx(0.4) and p.counts["cos_full_decoupled"] == 5
    assert p.medians["grad_norm_render_term"] == pytest.approx(0.8)
    assert p.medians["grad_norm_full_hard/grad_norm_full_soft"] == pytest.approx(0.25)  # 0.25 x 4, 0.5 once
    assert p.medians["cos_hard_decoupled"] is None and p.counts["cos_hard_decoupled"] == 0
    assert p.all_cos == pytest.approx(0.85)  # median of all eight: (0.8 + 0.9) / 2
    text = "\n".join(seeds.probe_section(runs, tmp_path))
    assert "above 0.1 x the run's first probe's" in text
    assert "| hopper | full-soft | 5/8 (s0: 3/5, s1: 2/3) | 0.4 (n=5) | 0.8 (n=5) | 0.5 (n=5) | - | - |" in text
    # the blind phase: seed 0 stops looking at 20 and 40 (lowest 0.01 / 6), seed 1 at 20 (0.05 / 1)
    assert (p.blind[0].blind, p.blind[0].probes, p.blind[0].looks_again_at, p.blind[0].last_blind) == (2, 4, 30, 40)
    assert p.blind[0].lowest == pytest.approx(0.01 / 6) and p.blind[1].lowest == pytest.approx(0.05)
    assert ("| hopper | full-soft | s0: 2/4, s1: 1/2 | 0.026 (s0: 0.0017, s1: 0.05) | s0: 30, s1: 30 | s0: 40, s1: 20 |"
            in text)
    assert "No run has probe iterations" in "\n".join(seeds.probe_section([load_run(parent / "blind0")], tmp_path))


def test_the_training_return_collapse_rate_counts_falls_below_half_the_best_so_far():
    # returns 0 (no positive best yet), 100, 40 (below 50), 60, 120, 50 (below 60), 200 (past `until`)
    rows = [{"iter": i, "return_mean": v} for i, v in zip(range(10, 80, 10), (0.0, 100.0, 40.0, 60.0, 120.0, 50.0,
                                                                               200.0))]
    rows.insert(1, {"iter": 15, "return_mean": None})  # no finished episode on this line
    run = Run(path=Path("r"), config={"task": "hopper", "seed": 0, "mode": "decoupled"}, environment={},
              command=None, summary=None, metrics=rows)
    assert seeds.training_collapse_rate(run, until=60) == pytest.approx(2 / 4)  # after the first positive best
    assert np.isnan(seeds.training_collapse_rate(run, until=10))  # no positive best


def test_the_blind_phase_table_says_what_it_could_not_tell():
    from ablations.reports.stats import BlindPhase

    phases = {0: BlindPhase(500, 2, 0, None, None),  # a first probe of 0: no bar
              1: BlindPhase(500, 4, 4, 0.01, None, 401),  # blind on every probe of the window
              2: BlindPhase(500, 3, 0, 0.5, None)}  # always looking
    probes = seeds.ArmProbes("hopper", "decoupled", {0: 1, 1: 1, 2: 3}, {0: 3, 1: 5, 2: 4}, {}, {}, None, phases)
    row = next(ln for ln in seeds._blind_phase_lines([probes], 0.1) if ln.startswith("| hopper"))
    assert row == ("| hopper | decoupled | s0: -/2, s1: 4/4, s2: 0/3 | 0.26 (s0: -, s1: 0.01, s2: 0.5) | "
                   "s0: no bar (first probe 0), s1: still blind at its last probe (401), s2: never blind | "
                   "s0: -, s1: 401, s2: - |")


def test_the_section_reads_no_arm_from_fewer_than_three_seeds(tmp_path):
    parent = tmp_path / "runs"
    dec = DEC
    # hopper: the gate passes on ten seeds; full-hard-dva has one, far above decoupled
    _task(parent, "hopper", dec, [d - 800.0 for d in dec], **{"full-hard-dva": [9000.0]})
    # ant: one seed of each, decoupled far above blind: a point, not an interval
    _task(parent, "ant", [2000.0], [100.0])
    runs = find_runs([parent])
    text = "\n".join(seeds.seed_section(runs, tmp_path / "figs", tmp_path, floors=load_floors(), reps=REPS))
    parts = dict(part.split("\n", 1) for part in text.split("\n### ")[1:])
    assert "full-hard-dva: too few paired seeds to read (fewer than 3)" in parts["hopper"]
    assert "better than decoupled" not in parts["hopper"]
    assert ("too few seeds to read decoupled against blind: 1 paired seed(s), and no verdict rests on fewer than 3 "
            "(decoupled minus blind 1900 [1900, 1900]); the pixel arms cannot be ranked on this task yet"
            ) in parts["ant"]


def test_runs_read_at_an_earlier_iteration(tmp_path):
    # evaluations at 10 and 20: at 20 full-soft is far ahead of decoupled, at 10 far behind
    parent = tmp_path / "runs"
    for s_, d in enumerate(DEC):
        write_run(parent, f"dec{s_}", seed=s_, evals=[d, d + 10.0], iters=20)
        write_run(parent, f"blind{s_}", mode="blind", seed=s_, evals=[d - 500.0, d - 500.0], iters=20)
        write_run(parent, f"full{s_}", mode="full", seed=s_, evals=[d - 300.0 + s_, d + 600.0 + s_], iters=20)
    runs = find_runs([parent])
    whole = seeds.seed_statistics(runs, reps=REPS)["hopper"]
    early = seeds.seed_statistics(runs, reps=REPS, at_iteration=10)["hopper"]
    assert whole.stats.iteration == 20 and whole.verdicts["equal iterations"].readings == {"full-soft": "better"}
    assert early.stats.iteration == 10 and early.verdicts["equal iterations"].readings == {"full-soft": "worse"}
    assert early.stats.whole.arms["full-soft"].final == {s_: d - 300.0 + s_ for s_, d in enumerate(DEC)}
    # beyond the runs' end it changes nothing; the section says where it read them
    assert seeds.seed_statistics(runs, reps=REPS, at_iteration=500)["hopper"].stats.iteration == 20
    text = "\n".join(seeds.seed_section(runs, tmp_path / "f", tmp_path, reps=REPS, at_iteration=10))
    assert "**Read at iteration 10** (`--at-iteration`)" in text and "**Verdict (equal iterations, 10):**" in text
    with pytest.raises(ValueError, match="at_iteration must be a positive number of iterations, got 0"):
        seeds.seed_statistics(runs, reps=REPS, at_iteration=0)


def test_the_state_arm_does_not_set_the_wall_clock_budget(tmp_path):
    # decoupled 20 iterations x 40 ms = 0.8 s, blind 20 x 70 ms = 1.4 s, state 20 x 10 ms = 0.2 s: the budget is
    # decoupled's 0.8 s (state's 0.2 s would leave the pixel arms without an evaluation), blind cut at its 11th
    # iteration (0.77 s: between iterations, not ended), state read at its end
    parent = tmp_path / "runs"
    for arm, mode, ms in (("decoupled", "decoupled", 40.0), ("blind", "blind", 70.0), ("state", "state", 10.0)):
        for s in range(3):
            write_run(parent, f"hopper_{arm}_{s}", mode=mode, seed=s, evals=[100.0 * s, 200.0 + s], iters=20,
                      iter_ms=ms)
    runs = find_runs([parent])
    out = seeds.seed_statistics(runs, reps=REPS)
    ts = out["hopper"].stats
    assert ts.wall_s == pytest.approx(0.8)
    assert ts.iters_at_wall == {"decoupled": 20, "blind": 11, "state": 20}
    assert ts.equal_wall.arms["state"].final == ts.whole.arms["state"].final
    text = "\n".join(seeds.seed_section(runs, tmp_path / "figs", tmp_path, reps=REPS, computed=out))
    assert "read at their end" in text and "The runs of state (the actor on the state vector" in text


def test_a_state_arm_without_a_time_alone_leaves_only_itself_out_of_equal_wall_clock(tmp_path):
    # population members (no time of their own); the benchmark times the state arm at 64 envs, its runs trained
    # 256 (SHAC's hopper): that row is not its time, so state leaves the equal-wall-clock view and the pixel arms
    # keep it; a pixel arm without a time still takes the whole view away
    parent = tmp_path / "runs"
    for arm, mode in (("decoupled", "decoupled"), ("blind", "blind"), ("state", "state")):
        for s in range(3):
            write_run(parent, f"hopper_{arm}_{s}", mode=mode, seed=s, evals=[100.0 * s, 200.0 + s], iters=20,
                      members=["a", "b"], settings={"num_envs": 256} if mode == "state" else None)
    runs = find_runs([parent])
    common = {"task": "hopper", "horizon": 32, "image_size": 84, "compile": True}
    rows = [{**common, "mode": "decoupled", "raster_model": "softmax", "iter_ms": 40.0, "num_envs": 64},
            {**common, "mode": "blind", "raster_model": None, "iter_ms": 70.0, "num_envs": 64},
            {**common, "mode": "state", "raster_model": None, "iter_ms": 10.0, "num_envs": 64}]
    bench = tmp_path / "iteration.json"
    bench.write_text(json.dumps({"gpu": "GPU-B", "results": rows}))
    t = arms.iteration_times(runs, arms.arm_label(runs), [bench])["hopper"]
    assert t.ms == {"decoupled": 40.0, "blind": 70.0} and t.untimed == ("state",)
    assert "state left out: no time measured alone at its runs' settings, trained as population members" in t.why
    out = seeds.seed_statistics(runs, benchmarks=[bench], reps=REPS)
    ts = out["hopper"].stats
    assert ts.wall_s == pytest.approx(0.8) and set(ts.equal_wall.arms) == {"decoupled", "blind"}
    assert ts.untimed_at_wall == ("state",) and "state" in ts.equal_iters.arms
    text = "\n".join(seeds.seed_section(runs, tmp_path / "figs", tmp_path, reps=REPS, computed=out))
    assert "Equal wall-clock: every run of the timed arms cut at 0.8 s" in text and "state left out" in text
    # a state time measured on another device is no time beside the others': state alone is left out again
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"gpu": "GPU-C", "results": [{**rows[2], "num_envs": 256, "iter_ms": 30.0}]}))
    t = arms.iteration_times(runs, arms.arm_label(runs), [bench, other])["hopper"]
    assert t.ms == {"decoupled": 40.0, "blind": 70.0} and t.untimed == ("state",)
    assert "its only time is from benchmark other.json on GPU-C" in t.why
    # timed at its own settings, state is in the view again
    bench.write_text(json.dumps({"gpu": "GPU-B", "results": [*rows, {**rows[2], "num_envs": 256, "iter_ms": 30.0}]}))
    t = arms.iteration_times(runs, arms.arm_label(runs), [bench])["hopper"]
    assert t.ms == {"decoupled": 40.0, "blind": 70.0, "state": 30.0} and t.untimed == ()
    bench.write_text(json.dumps({"gpu": "GPU-B", "results": rows[1:]}))
    t = arms.iteration_times(runs, arms.arm_label(runs), [bench])["hopper"]
    assert t.ms is None and "decoupled, state: trained as population members" in t.why
    assert seeds.seed_statistics(runs, benchmarks=[bench], reps=REPS)["hopper"].stats.equal_wall is None
