"""ablate-plot: figures from fixture run folders, mean +- std across seeds, clear errors for bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from matplotlib.colors import to_rgb

from ablations.reports import plot, style
from ablations.reports.plot import FIGURES, aggregate, build_figures, make_plots
from ablations.reports.style import group_runs, load_floors
from ablations.run_folder import find_runs, load_run
from tests.ablations.conftest import write_run

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def runs_dir(tmp_path):
    parent = tmp_path / "runs"
    for seed in (0, 1):
        write_run(parent, task="cartpole", mode="full", seed=seed)
        write_run(parent, task="cartpole", mode="decoupled", seed=seed)
    write_run(parent, task="hopper", mode="decoupled", seed=0, gpu="NVIDIA H100")
    write_run(parent, task="hopper", mode="state", seed=0, probe_every=0)

    def noise_and_evaluations(m):
        m["action_std"] = 0.4 - 0.01 * m["iter"]
        if m["iter"] % 5 == 0:
            m.update(eval_return_mean=10.0 * m["iter"], eval_return_std=1.0, eval_length_mean=100.0)

    for run in parent.iterdir():
        _rewrite_metrics(run, noise_and_evaluations)
    return parent


def test_aggregate_mean_and_sample_std():
    x = np.arange(5.0)
    gx, c, lo, hi, n = aggregate([(x, np.full(5, 1.0)), (x, np.full(5, 3.0))])
    np.testing.assert_array_equal(n, 2)
    np.testing.assert_array_equal(gx, x)
    np.testing.assert_allclose(c, 2.0)
    np.testing.assert_allclose(hi - c, np.sqrt(2.0))  # sample std (ddof=1) of {1, 3}
    np.testing.assert_allclose(c - lo, np.sqrt(2.0))


def test_aggregate_covers_every_runs_own_range_with_the_count_per_point():
    a = (np.array([0.0, 2.0, 4.0]), np.array([0.0, 2.0, 4.0]))
    b = (np.array([1.0, 3.0, 5.0]), np.array([1.0, 3.0, 5.0]))
    gx, c, lo, hi, n = aggregate([a, b])
    np.testing.assert_array_equal(gx, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0])  # each run over its own range
    np.testing.assert_array_equal(n, [1, 2, 2, 2, 2, 1])
    np.testing.assert_allclose(c, gx)  # both are y = x, linearly interpolated
    np.testing.assert_allclose(hi - lo, 0.0, atol=1e-12)
    gx, c, _, _, n = aggregate([(np.array([0.0, 1.0]), np.array([0.0, 1.0])), (np.array([2.0, 3.0]), np.ones(2))])
    np.testing.assert_array_equal(n, [1, 1, 1, 1]) and np.testing.assert_allclose(c, [0.0, 1.0, 1.0, 1.0])
    assert aggregate([(np.array([]), np.array([]))]) is None


def test_aggregate_log_space_is_geometric():
    x = np.arange(3.0)
    _, c, lo, hi, _ = aggregate([(x, np.full(3, 1.0)), (x, np.full(3, 100.0))], log=True)
    np.testing.assert_allclose(c, 10.0)  # geometric mean of 1 and 100
    np.testing.assert_allclose(hi / c, c / lo)  # a multiplicative band
    assert (lo > 0).all()


def test_load_and_group(runs_dir):
    runs = find_runs([runs_dir])  # a parent of run folders stands for all of them
    assert len(runs) == 6
    groups = group_runs(runs)
    assert list(groups) == [("cartpole", "full"), ("cartpole", "decoupled"), ("hopper", "decoupled"),
                            ("hopper", "state")]
    assert [r.seed for r in groups[("cartpole", "full")]] == [0, 1]
    x, y = groups[("cartpole", "full")][1].series("env_steps", "return_mean")
    assert x[0] == 3 * 4 * 8 and y[0] == 31.0  # iterations without a return are skipped


def test_make_plots_writes_every_figure_with_mean_and_std(runs_dir, tmp_path, monkeypatch):
    seen = []
    real = plot.aggregate

    def spy(series, **kw):
        seen.append(len(series))
        return real(series, **kw)

    monkeypatch.setattr(plot, "aggregate", spy)
    out = tmp_path / "plots"
    res = make_plots(find_runs([runs_dir]), out)
    assert set(res.files) == set(FIGURES) and not res.skipped
    for name in FIGURES:
        data = (out / name).read_bytes()
        assert data[:8] == PNG and len(data) > 5000, name
    assert 2 in seen, "the two seeds of a group are aggregated together"


def test_make_plots_skips_figures_without_data(tmp_path):
    run = write_run(tmp_path / "runs", task="ant", mode="state", seed=0, probe_every=0)
    res = make_plots([load_run(run)], tmp_path / "plots")
    assert "cosine_hist.png" in res.skipped and "cosine_vs_iter.png" in res.skipped
    assert not (tmp_path / "plots" / "cosine_hist.png").exists()
    assert "return_vs_env_steps.png" in res.files
    # no evaluation, no exploration noise logged, no probe: those figures are skipped too
    assert {"eval_return_vs_iter.png", "exploration_noise.png", "looking.png"} <= set(res.skipped)


def test_bad_input_is_a_clear_error(tmp_path, capsys):
    from ablations.cli import plot_main

    with pytest.raises(ValueError, match="no run folders given"):
        find_runs([])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"not a run folder: it has no config\.json"):
        find_runs([tmp_path / "empty"])
    with pytest.raises(ValueError, match="no such folder"):
        load_run(tmp_path / "missing")
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(ValueError, match="is a file, not a run folder"):
        load_run(tmp_path / "file.txt")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "config.json").write_text("{\"lr\": 1}")
    with pytest.raises(ValueError, match="no 'config' object"):
        load_run(tmp_path / "bad")

    for argv, msg in (([], "no run folders given"), ([str(tmp_path / "empty")], "not a run folder")):
        with pytest.raises(SystemExit) as e:
            plot_main(argv)
        assert e.value.code == 2 and msg in capsys.readouterr().err


def test_cli_writes_pngs(runs_dir, tmp_path, capsys):
    from ablations.cli import plot_main

    out = tmp_path / "figs"
    runs = sorted(str(p) for p in runs_dir.iterdir())
    plot_main([*runs, "--out", str(out)])
    printed = capsys.readouterr().out.split()
    assert sorted(printed) == sorted(str(out / n) for n in FIGURES)


def test_blind_has_a_colour_and_variants_get_labels(tmp_path):
    parent = tmp_path / "runs"
    for seed in (0, 1):
        write_run(parent, task="hopper", mode="full", seed=seed, name=f"hard{seed}",
                  settings={"preset": "shac-diffrender", "raster_model": "hard", "renderer": "soft"})
        write_run(parent, task="hopper", mode="full", seed=seed, name=f"alpha{seed}",
                  settings={"preset": "dva", "raster_model": "alpha", "renderer": "soft"})
    write_run(parent, task="hopper", mode="decoupled", seed=0, settings={"preset": "dva", "raster_model": "alpha"})
    write_run(parent, task="hopper", mode="blind", seed=0, probe_every=0)
    runs = find_runs([parent])
    assert style.MODE_COLORS["blind"] not in {c for m, c in style.MODE_COLORS.items() if m != "blind"}
    groups = group_runs(runs)
    # Only the settings that differ within a mode make it into its label.
    assert list(groups) == [("hopper", "full (dva, alpha)"), ("hopper", "full (shac-diffrender, hard)"),
                            ("hopper", "decoupled"), ("hopper", "blind")]
    assert [r.path.name for r in groups[("hopper", "full (shac-diffrender, hard)")]] == ["hard0", "hard1"]
    styles = style.arm_styles(groups)
    full_a, full_h = styles["full (dva, alpha)"], styles["full (shac-diffrender, hard)"]
    # Variants of a mode share its hue (the first has the mode's colour itself) but no two arms look alike.
    assert full_a.color == to_rgb(style.MODE_COLORS["full"]) and full_h.color != full_a.color
    assert full_h.color[0] == max(full_h.color), "a shade of the mode's red"
    for part in ("color", "linestyle", "marker"):
        assert len({getattr(st, part) for st in styles.values()}) == len(styles), part
    # A caller's labels (ablate-paper's arms) replace them.
    named = group_runs(runs, label=lambda r: "arm-" + r.mode)
    assert set(named) == {("hopper", "arm-full"), ("hopper", "arm-decoupled"), ("hopper", "arm-blind")}
    # The preset name falls back to config.json's preset record.
    run = runs[0]
    run.config.pop("preset")
    run.preset = {"name": "dva", "supplied": {}, "overridden": {}}
    assert run.setting("preset") == "dva"


def floors_file(path, tasks):
    path.write_text(json.dumps({"tasks": {t: {"zero": {"mean": z, "std": 1.0, "episodes": 8},
                                              "random": {"mean": r, "std": 2.0, "episodes": 8}}
                                          for t, (z, r) in tasks.items()}}))
    return path


def test_floors_are_drawn_beside_every_return_curve(runs_dir, tmp_path):
    floors = load_floors(floors_file(tmp_path / "floors.json", {"cartpole": (5.0, 7.0)}))
    with pytest.warns(UserWarning, match=r"no return floor for task 'hopper'.*task-floors --tasks hopper"):
        figs = build_figures(find_runs([runs_dir]), floors=floors)
    try:
        # Once per task, although three figures draw hopper's return.
        assert figs.warnings == [floors.missing_message("hopper")]
        for name, fig in figs.figures.items():
            cartpole, hopper = fig.axes[:2]
            drawn = {ln.get_gid(): ln.get_ydata()[0] for ln in cartpole.lines if str(ln.get_gid()).startswith("floor")}
            if name.startswith(("return_", "eval_return_")):
                assert drawn == {"floor:zero": 5.0, "floor:random": 7.0}, name
                # named on the figure beside the line, the higher floor above the lower
                texts = {t.get_text(): t.get_va() for t in cartpole.texts if t.get_gid() != "count"}
                assert texts == {"zero action\nfloor 5": "top", "random action\nfloor 7": "bottom"}
                assert not any(str(ln.get_gid()).startswith("floor") for ln in hopper.lines)
            else:
                assert not drawn, name
    finally:
        figs.close()


def test_default_floors_are_this_checkouts(tmp_path):
    floors = load_floors()
    assert floors.source == style.DEFAULT_FLOORS
    assert floors.of("hopper")["zero"]["mean"] == json.loads(style.DEFAULT_FLOORS.read_text())[
        "tasks"]["hopper"]["zero"]["mean"]
    assert floors.of("no-such-task") is None


def test_bad_floors_files_are_named(tmp_path):
    with pytest.raises(ValueError, match=r"--floors .*missing\.json: no such file"):
        load_floors(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="cannot be read"):
        load_floors(tmp_path / "bad.json")
    (tmp_path / "flat.json").write_text(json.dumps({"hopper": 1}))
    with pytest.raises(ValueError, match="expected a 'tasks' object"):
        load_floors(tmp_path / "flat.json")
    (tmp_path / "nomean.json").write_text(json.dumps({"tasks": {"hopper": {"zero": {"std": 1}}}}))
    with pytest.raises(ValueError, match="task 'hopper' needs zero/random objects with a numeric 'mean'"):
        load_floors(tmp_path / "nomean.json")


def test_probe_figures_are_skipped_without_probe_metrics(tmp_path):
    run = write_run(tmp_path / "runs", task="ant", mode="blind", seed=0, probe_every=0)
    res = make_plots([load_run(run)], tmp_path / "plots")
    for name in ("probe_grad_norms.png", "render_term_groups.png", "image_sensitivity.png"):
        assert name in res.skipped and not (tmp_path / "plots" / name).exists()
    assert "image_sensitivity_f" in res.skipped["image_sensitivity.png"]


@pytest.mark.slow
def test_plot_runs_reads_the_floors_flag(runs_dir, tmp_path):
    from ablations.reports import PlotConfig, plot_runs

    floors = floors_file(tmp_path / "f.json", {"cartpole": (1.0, 2.0), "hopper": (3.0, 4.0)})
    res = plot_runs(PlotConfig(runs=(runs_dir,), out=tmp_path / "p", floors=floors))
    assert not res.warnings and "return_vs_iter.png" in res.files
    with pytest.raises(ValueError, match="no such file"):
        plot_runs(PlotConfig(runs=(runs_dir,), out=tmp_path / "p", floors=tmp_path / "none.json"))


# ------------------------------------------------------------------------------------- what the figures show
def _dashes(line):
    """A line's dash pattern: Line2D's public getter names every custom pattern just '--'."""
    return line._unscaled_dash_pattern


def _arm_lines(ax):
    """The arms' curves of a panel (not floors, evaluations or histogram patches)."""
    return [ln for ln in ax.lines if ln.get_gid() in (None, "arm") and not ln.get_label().startswith("_")]


def _rewrite_metrics(run, change):
    lines = [json.loads(s) for s in (run / "metrics.jsonl").read_text().splitlines()]
    for m in lines:
        change(m)
    (run / "metrics.jsonl").write_text("".join(json.dumps(m) + "\n" for m in lines))


@pytest.fixture
def arms_dir(tmp_path):
    """Six hopper arms as ablate-paper runs them (three full variants, decoupled, state, blind), two seeds each,
    60 iterations (dense curves); seed 0 of decoupled evaluates as `ablate` does (mean and std over episodes),
    seed 0 of state as older runs did (eval_return only)."""
    parent = tmp_path / "arms"
    variants = {"alpha": {"raster_model": "alpha"}, "softmax": {"raster_model": "softmax"},
                "hard": {"raster_model": "hard"}}
    for seed in (0, 1):
        for name, settings in variants.items():
            write_run(parent, task="hopper", mode="full", seed=seed, iters=60, name=f"full-{name}{seed}",
                      settings=settings)
        for mode in ("decoupled", "state", "blind"):
            write_run(parent, task="hopper", mode=mode, seed=seed, iters=60, settings={"raster_model": "alpha"})

    def evaluate(m):
        if m["iter"] % 30 == 0:
            m.update(eval_return_mean=500.0 + m["iter"], eval_return_std=25.0, eval_length_mean=300.0)

    def evaluate_old(m):
        if m["iter"] == 60:
            m.update(eval_return=900.0, eval_steps=300)

    _rewrite_metrics(parent / "hopper_decoupled_seed0", evaluate)
    _rewrite_metrics(parent / "hopper_state_seed0", evaluate_old)
    return parent


@pytest.fixture
def arm_figures(arms_dir, tmp_path):
    floors = load_floors(floors_file(tmp_path / "floors.json", {"hopper": (150.0, -40.0)}))
    runs = find_runs([arms_dir])
    figs = build_figures(runs, floors=floors)
    yield figs, style.arm_styles(group_runs(runs))
    figs.close()


def test_every_arm_has_a_style_of_its_own(arm_figures):
    figs, styles = arm_figures
    assert len(styles) == 6
    for name in ("return_vs_iter.png", "return_vs_env_steps.png", "grad_norm.png", "memory.png"):
        ax = figs.figures[name].axes[0]
        lines = _arm_lines(ax)
        assert [ln.get_label() for ln in lines] == list(styles), name
        for ln in lines:
            assert to_rgb(ln.get_color()) == styles[ln.get_label()].color, name
        for part in (lambda ln: to_rgb(ln.get_color()), _dashes, lambda ln: ln.get_marker()):
            assert len({part(ln) for ln in lines}) == len(lines), name
        # Dense curves carry a dozen markers, each arm's on other points, so lines on top of each other show.
        marks = [ln.get_markevery() for ln in lines]
        assert all(m[1] == math.ceil(len(ln.get_xdata()) / 12) for m, ln in zip(marks, lines)), (name, marks)
        assert len({m[0] for m in marks}) > 1, name
    timing = figs.figures["timing.png"]
    assert len(timing.axes) == 2 and all(len(_arm_lines(ax)) == 6 for ax in timing.axes)


def test_one_legend_outside_the_panels(arm_figures):
    figs, styles = arm_figures
    # one figure of each kind (drawing all eleven takes seconds)
    for name in ("return_vs_iter.png", "probe_grad_norms.png", "cosine_hist.png", "timing.png"):
        fig = figs.figures[name]
        fig.canvas.draw()
        assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes), name
        legend = fig.legends[0].get_window_extent()
        for ax in fig.axes:
            assert not legend.overlaps(ax.get_window_extent()), name
    texts = [t.get_text() for t in figs.figures["return_vs_iter.png"].legends[0].get_texts()]
    # six arms, then what the line and the stars are: eight entries
    assert texts == [f"{lab} (n=2)" for lab in styles] + ["line: training return (last 100 episodes)",
                                                          "star: deterministic evaluation (each run)"]


def test_evaluations_are_drawn_beside_the_training_return(arm_figures, arms_dir):
    figs, styles = arm_figures
    for name, x in (("return_vs_iter.png", "iter"), ("return_vs_wall_clock.png", "wall_s")):
        ax = figs.figures[name].axes[0]
        stars = {to_rgb(ln.get_color()): ln for ln in ax.lines if ln.get_gid() == "evaluation"}
        assert set(stars) == {styles["decoupled"].color, styles["state"].color}, name
        assert all(ln.get_marker() == "*" and ln.get_linestyle() == "None" for ln in stars.values())
        new = stars[styles["decoupled"].color]
        np.testing.assert_array_equal(new.get_ydata(), [530.0, 560.0])
        assert list(new.get_xdata()) == list(load_run(arms_dir / "hopper_decoupled_seed0").evaluations(x)[0])
        np.testing.assert_array_equal(stars[styles["state"].color].get_ydata(), [900.0])  # eval_return
        with_bars = [c for c in ax.containers if c.has_yerr]
        assert len(with_bars) == 1  # the std over episodes exists only where the run recorded it
        segments = with_bars[0].lines[2][0].get_segments()
        np.testing.assert_allclose([s[1][1] - s[0][1] for s in segments], [50.0, 50.0])
    assert "eval" not in str([ln.get_label() for ln in _arm_lines(figs.figures["grad_norm.png"].axes[0])])


def test_run_evaluations_read_new_and_old_metrics(arms_dir):
    x, mean, std = load_run(arms_dir / "hopper_decoupled_seed0").evaluations("env_steps")
    np.testing.assert_array_equal(x, [30 * 32, 60 * 32])
    np.testing.assert_array_equal(mean, [530.0, 560.0])
    np.testing.assert_array_equal(std, [25.0, 25.0])
    x, mean, std = load_run(arms_dir / "hopper_state_seed0").evaluations("iter")
    assert list(x) == [60] and list(mean) == [900.0] and np.isnan(std).all()
    assert len(load_run(arms_dir / "hopper_blind_seed0").evaluations("iter")[0]) == 0


def test_cosine_is_one_minus_cos_on_a_log_axis_with_every_probe_marked(runs_dir):
    figs = build_figures(find_runs([runs_dir]), floors=load_floors())
    try:
        ax = figs.figures["cosine_vs_iter.png"].axes[0]
        assert ax.get_yscale() == "log"
        full = next(ln for ln in _arm_lines(ax) if ln.get_label() == "full")
        assert full.get_marker() not in (None, "None", "") and full.get_markevery() is None
        # probes at iterations 1, 4, 7, 10; the geometric mean of 1 - cos over seeds 0 and 1
        np.testing.assert_array_equal(full.get_xdata(), [1, 4, 7, 10])
        it = np.array([1, 4, 7, 10])
        np.testing.assert_allclose(full.get_ydata(), np.sqrt((1 - np.cos(0.1 * it)) * (1 - np.cos(0.1 * it + 1))))
        hist = figs.figures["cosine_hist.png"].axes[0]
        assert hist.get_xscale() == "log" and hist.get_xlim()[1] >= 2.0
        for name in ("probe_grad_norms.png", "render_term_groups.png", "image_sensitivity.png"):
            lines = _arm_lines(figs.figures[name].axes[0])
            assert lines and all(ln.get_marker() not in (None, "None", "") and ln.get_markevery() is None
                                 for ln in lines), name
    finally:
        figs.close()


def test_quantities_lying_on_each_other_stay_visible(tmp_path):
    """The quick start's probe figure: one decoupled run, whose full and decoupled norms are the same."""
    run = write_run(tmp_path / "runs", task="cartpole", mode="decoupled", seed=0)
    _rewrite_metrics(run, lambda m: m.update(grad_norm_decoupled=m["grad_norm_full"]) if m["probed"] else None)
    figs = build_figures([load_run(run)], floors=load_floors())
    try:
        fig = figs.figures["probe_grad_norms.png"]
        full, decoupled, _render_term = _arm_lines(fig.axes[0])
        np.testing.assert_array_equal(full.get_ydata(), decoupled.get_ydata())
        # the one underneath is wider, with larger markers of another shape
        assert full.get_linewidth() > decoupled.get_linewidth() and full.get_markersize() > decoupled.get_markersize()
        assert full.get_marker() != decoupled.get_marker() and full.get_markerfacecolor() == "none"
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
        assert labels == ["full gradient", "decoupled gradient", "render term", "decoupled (n=1)"]
    finally:
        figs.close()


def test_linear_axes_print_plain_ticks(tmp_path):
    """Values that differ only in the sixth digit get no offset label such as 1e-5+9.9999e-1."""
    run = write_run(tmp_path / "runs", task="cartpole", mode="state", seed=0, probe_every=0)
    _rewrite_metrics(run, lambda m: m.update(return_mean=0.99999 + 1e-7 * m["iter"]))
    with pytest.warns(UserWarning, match="no return floor"):  # floors would widen the axis: none here
        figs = build_figures([load_run(run)], floors=load_floors(floors_file(tmp_path / "f.json", {})))
    try:
        fig = figs.figures["return_vs_iter.png"]
        fig.canvas.draw()
        ax = fig.axes[0]
        assert ax.get_yscale() == "linear" and ax.yaxis.get_offset_text().get_text() == ""
        assert all(t.get_text() for t in ax.get_yticklabels())
    finally:
        figs.close()


def test_runs_differing_per_panel_say_so(tmp_path):
    parent = tmp_path / "runs"
    for seed in (0, 1):
        write_run(parent, task="cartpole", mode="decoupled", seed=seed)
    write_run(parent, task="hopper", mode="decoupled", seed=0)
    figs = build_figures(find_runs([parent]), floors=load_floors())
    try:
        assert [t.get_text() for t in figs.figures["grad_norm.png"].legends[0].get_texts()] == ["decoupled (n=2/1)"]
        hist = [t.get_text() for t in figs.figures["cosine_hist.png"].legends[0].get_texts()]
        assert hist == ["decoupled (n=2/1, 8/4 probes)"]
    finally:
        figs.close()


def test_evaluations_noise_and_looking_over_iterations(runs_dir):
    # seed 1 of cartpole full stops looking at iteration 4: its sensitivity falls to a hundredth of the first
    _rewrite_metrics(runs_dir / "cartpole_full_seed1", lambda m: m.update(
        image_sensitivity_f0=0.001, image_sensitivity_f1=0.002, image_sensitivity_f2=0.004) if m["iter"] == 4 else None)
    figs = build_figures(find_runs([runs_dir]), floors=load_floors())
    try:
        cartpole = figs.figures["eval_return_vs_iter.png"].axes[0]
        assert len([ln for ln in cartpole.lines if ln.get_gid() == "run"]) == 4  # every seed of both arms, thin
        full = next(ln for ln in _arm_lines(cartpole) if ln.get_label() == "full")
        np.testing.assert_array_equal(full.get_xdata(), [5, 10])
        np.testing.assert_array_equal(full.get_ydata(), [50.0, 100.0])  # the mean over the seeds' evaluations
        legend = [t.get_text() for t in figs.figures["eval_return_vs_iter.png"].legends[0].get_texts()]
        assert "thin: each seed" in legend
        noise = next(ln for ln in _arm_lines(figs.figures["exploration_noise.png"].axes[0]) if ln.get_label() == "full")
        np.testing.assert_allclose(noise.get_ydata(), 0.4 - 0.01 * noise.get_xdata())
        fig = figs.figures["looking.png"]
        ax = fig.axes[0]
        assert ax.get_yscale() == "log"
        bar = [ln for ln in ax.lines if ln.get_gid() == "reference"]
        assert len(bar) == 1 and bar[0].get_ydata()[0] == 0.1
        full = next(ln for ln in _arm_lines(ax) if ln.get_label() == "full")
        # probes at 1, 4, 7, 10 relative to each run's first; at 4 the geometric mean of 1 and 0.01
        np.testing.assert_array_equal(full.get_xdata(), [1, 4, 7, 10])
        np.testing.assert_allclose(full.get_ydata(), [1.0, 0.1, 1.0, 1.0])
        assert "looking bar: 0.1 x the first probe's" in [t.get_text() for t in fig.legends[0].get_texts()]
    finally:
        figs.close()


# ---------------------------------------------------------------------------- nothing lost, nothing hidden
def _lengths_dir(tmp_path):
    """The quick start's situation: three arms of different lengths (10, 40, 25 iterations), and within
    decoupled two seeds of different lengths (40 and 20)."""
    parent = tmp_path / "lengths"
    write_run(parent, task="cartpole", mode="full", seed=0, iters=10)
    write_run(parent, task="cartpole", mode="decoupled", seed=0, iters=40)
    write_run(parent, task="cartpole", mode="decoupled", seed=1, iters=20)
    write_run(parent, task="cartpole", mode="state", seed=0, iters=25, probe_every=0)
    return parent


def test_arms_of_different_lengths_are_all_drawn_over_their_own_ranges(tmp_path):
    figs = build_figures(find_runs([_lengths_dir(tmp_path)]), floors=load_floors())
    try:
        # return_mean starts at iteration 3 (no finished episode before)
        assert figs.drawn["return_vs_iter.png"] == {("cartpole", "full"): (3.0, 10.0, 1),
                                                    ("cartpole", "decoupled"): (3.0, 40.0, 2),
                                                    ("cartpole", "state"): (3.0, 25.0, 1)}
        assert figs.drawn["grad_norm.png"][("cartpole", "decoupled")] == (1.0, 40.0, 2)
        ax = figs.figures["return_vs_iter.png"].axes[0]
        assert [ln.get_label() for ln in _arm_lines(ax)] == ["full", "decoupled", "state"]
        dec = next(ln for ln in _arm_lines(ax) if ln.get_label() == "decoupled")
        # the full line where both seeds cover the iteration, the dotted one on to seed 0's end, n where it changes
        y = np.asarray(dec.get_ydata(), float)
        assert dec.get_xdata()[-1] == 40 and np.isnan(y[-1]) and not np.isnan(y[dec.get_xdata().tolist().index(20)])
        fewer = next(ln for ln in ax.lines if ln.get_gid() == "fewer runs")
        assert fewer.get_xdata()[-1] == 40 and fewer.get_linestyle() == ":"
        assert sorted(t.get_text() for t in ax.texts if t.get_gid() == "count") == ["n=1", "n=2"]
        legend = [t.get_text() for t in figs.figures["return_vs_iter.png"].legends[0].get_texts()]
        assert "dotted: fewer of the arm's runs\ncover it (n where it changes)" in legend
        # the band only where two runs cover the iteration: up to 20
        band = next(c for c in ax.collections if c.get_paths() and c.get_paths()[0].vertices[:, 0].max() > 5)
        assert band.get_paths()[0].vertices[:, 0].max() <= 20
        # the probe figure keeps every probe of every run: decoupled probes at 1, 4, ..., 40
        cos = figs.drawn["cosine_vs_iter.png"]
        assert cos[("cartpole", "decoupled")] == (1.0, 40.0, 2) and cos[("cartpole", "full")] == (1.0, 10.0, 1)
        assert not figs.left_out or all("state" in line for line in figs.left_out)
    finally:
        figs.close()


def test_what_a_figure_cannot_draw_is_named_in_one_line(tmp_path):
    parent = _lengths_dir(tmp_path)
    _rewrite_metrics(parent / "cartpole_state_seed0", lambda m: m.pop("grad_norm"))
    figs = build_figures(find_runs([parent]), floors=load_floors())
    try:
        assert ("grad_norm.png: left out cartpole state (no run of theirs has both iter and grad_norm)"
                in figs.left_out)
        assert ("cosine_hist.png: left out cartpole state (no probe iterations: runs of modes that render nothing "
                "have none)" in figs.left_out)
        assert ("cartpole", "state") not in figs.drawn["grad_norm.png"]
    finally:
        figs.close()


def test_runs_sharing_a_seed_are_not_averaged_as_seeds(tmp_path, capsys):
    parent = tmp_path / "shared"
    write_run(parent, task="cartpole", mode="decoupled", seed=0, name="a")
    write_run(parent, task="cartpole", mode="decoupled", seed=0, name="b")
    write_run(parent, task="cartpole", mode="full", seed=0)
    runs = find_runs([parent])
    figs = build_figures(runs, floors=load_floors())
    try:  # the report's way: that arm left out of the figures, named
        assert figs.left_out[0] == (f"left out of every figure: arm 'decoupled' has two runs of task 'cartpole' with "
                                    f"seed 0: {parent / 'a'} and {parent / 'b'}; give one folder per seed")
        assert set(figs.drawn["return_vs_iter.png"]) == {("cartpole", "full")}
    finally:
        figs.close()
    # ablate-plot's way (the documented path runs one command twice): the run of the seed that started last is
    # drawn, the other named as left out
    from ablations.cli import plot_main

    (parent / "b" / "config.json").write_text(json.dumps(
        {**json.loads((parent / "b" / "config.json").read_text()), "started_utc": "2026-01-01T00:00:00+00:00"}))
    plot_main([str(parent), "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err.strip().splitlines()
    assert (f"left out of every figure: {parent / 'a'} (arm 'decoupled' of task 'cartpole' has another run of seed "
            f"0, {parent / 'b'}, started later; it is drawn)") in err
    assert (tmp_path / "p" / "return_vs_iter.png").exists()


@pytest.mark.slow
def test_figures_are_byte_identical_when_their_data_is(runs_dir, tmp_path):
    from ablations.reports.plot import plot_performance_profiles
    from ablations.reports.stats import PerformanceProfile, ProfileCurve

    runs = find_runs([runs_dir])
    first = make_plots(runs, tmp_path / "one", floors=load_floors())
    second = make_plots(runs, tmp_path / "two", floors=load_floors())
    assert first.files and set(first.files) == set(second.files)
    for name, path in first.files.items():
        data = path.read_bytes()
        assert data == second.files[name].read_bytes(), name
        assert b"matplotlib" not in data and b"Software\x00pixelgrad ablations" in data, name
    prof = PerformanceProfile("t", np.linspace(0, 1, 5), {"a": ProfileCurve(*[np.linspace(1, 0, 5)] * 3, 2)}, 10, 0, 3)
    assert plot_performance_profiles(prof, tmp_path / "p1.png").read_bytes() == \
        plot_performance_profiles(prof, tmp_path / "p2.png").read_bytes()
