"""ablate-plot: figures from fixture run folders, mean +- std across seeds, clear errors for bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ablations import plot
from ablations.plot import FIGURES, aggregate, find_runs, group_runs, load_floors, load_run, make_plots
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
    return parent


def test_aggregate_mean_and_sample_std():
    x = np.arange(5.0)
    gx, c, lo, hi = aggregate([(x, np.full(5, 1.0)), (x, np.full(5, 3.0))])
    np.testing.assert_array_equal(gx, x)
    np.testing.assert_allclose(c, 2.0)
    np.testing.assert_allclose(hi - c, np.sqrt(2.0))  # sample std (ddof=1) of {1, 3}
    np.testing.assert_allclose(c - lo, np.sqrt(2.0))


def test_aggregate_interpolates_onto_the_common_wall_clock_range():
    a = (np.array([0.0, 2.0, 4.0]), np.array([0.0, 2.0, 4.0]))
    b = (np.array([1.0, 3.0, 5.0]), np.array([1.0, 3.0, 5.0]))
    gx, c, lo, hi = aggregate([a, b])
    np.testing.assert_array_equal(gx, [1.0, 2.0, 3.0, 4.0])  # only where both runs have data
    np.testing.assert_allclose(c, gx)  # both are y = x, linearly interpolated
    np.testing.assert_allclose(hi - lo, 0.0, atol=1e-12)
    assert aggregate([(np.array([0.0, 1.0]), np.array([0.0, 1.0])), (np.array([2.0, 3.0]), np.ones(2))]) is None


def test_aggregate_log_space_is_geometric():
    x = np.arange(3.0)
    _, c, lo, hi = aggregate([(x, np.full(3, 1.0)), (x, np.full(3, 100.0))], log=True)
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
    assert plot.MODE_COLORS["blind"] not in {c for m, c in plot.MODE_COLORS.items() if m != "blind"}
    groups = group_runs(runs)
    # Only the settings that differ within a mode make it into its label.
    assert list(groups) == [("hopper", "full (dva, alpha)"), ("hopper", "full (shac-diffrender, hard)"),
                            ("hopper", "decoupled"), ("hopper", "blind")]
    assert [r.path.name for r in groups[("hopper", "full (shac-diffrender, hard)")]] == ["hard0", "hard1"]
    styles = plot._styles(groups)
    assert styles["full (dva, alpha)"][0] == styles["full (shac-diffrender, hard)"][0] == plot.MODE_COLORS["full"]
    assert styles["full (dva, alpha)"][1] != styles["full (shac-diffrender, hard)"][1]
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


def test_floors_are_drawn_beside_every_return_curve(runs_dir, tmp_path, monkeypatch):
    import matplotlib.axes

    drawn = []
    real = matplotlib.axes.Axes.axhline

    def spy(self, y=0, *args, **kw):
        drawn.append((self.get_title(), y, kw.get("label")))
        return real(self, y, *args, **kw)

    monkeypatch.setattr(matplotlib.axes.Axes, "axhline", spy)
    floors = load_floors(floors_file(tmp_path / "floors.json", {"cartpole": (5.0, 7.0)}))
    with pytest.warns(UserWarning, match=r"no return floor for task 'hopper'.*task-floors --tasks hopper"):
        res = make_plots(find_runs([runs_dir]), tmp_path / "plots", floors=floors)
    # Once per task, although three figures draw hopper's return.
    assert res.warnings == [floors.missing_message("hopper")]
    # Three return figures x the two floors of cartpole's panel; none elsewhere.
    assert sorted(drawn) == sorted([("cartpole", 5.0, "zero action floor (5)"),
                                    ("cartpole", 7.0, "random action floor (7)")] * 3)


def test_default_floors_are_this_checkouts(tmp_path):
    floors = load_floors()
    assert floors.source == plot.DEFAULT_FLOORS
    assert floors.of("hopper")["zero"]["mean"] == json.loads(plot.DEFAULT_FLOORS.read_text())[
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


def test_plot_runs_reads_the_floors_flag(runs_dir, tmp_path):
    from ablations.plot import PlotConfig, plot_runs

    floors = floors_file(tmp_path / "f.json", {"cartpole": (1.0, 2.0), "hopper": (3.0, 4.0)})
    res = plot_runs(PlotConfig(runs=(runs_dir,), out=tmp_path / "p", floors=floors))
    assert not res.warnings and "return_vs_iter.png" in res.files
    with pytest.raises(ValueError, match="no such file"):
        plot_runs(PlotConfig(runs=(runs_dir,), out=tmp_path / "p", floors=tmp_path / "none.json"))
