"""ablate-plot: figures from fixture run folders, mean +- std across seeds, clear errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest

from ablations import plot
from ablations.plot import FIGURES, aggregate, find_runs, group_runs, load_run, make_plots
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
