"""The documented path end to end, tiny: README step 3, then docs/quickstart.md sections 2, 3 and 5's population
and plots, in that order, in a fresh folder; every command exits without a refusal. The commands are read from
the documents; the substitutions that keep them tiny are stated in TINY (fewer iterations and environments, a
small image, no evaluation or video, one thread). The sweep of section 5 (Ray) and the GPU sections are left out:
tests/ablations/test_sweep.py runs sweeps."""

from __future__ import annotations

import glob
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: (what the documents say, what the test runs instead), applied to every ablate command.
TINY = ((r"--iters \d+ --num-envs \d+", "--iters 1 --num-envs 2"),
        (r"--device cpu$", "--device cpu --horizon 3 --image-size 24 --critic-iterations 1 --critic-batches 1 "
                           "--video-every 0 --eval-every 0 --cosine-every 0 --threads 1 --no-progress"))


def documented(path: str, start: str) -> str:
    """The first line of ``path`` that starts with ``start``, its shell comment dropped."""
    line = next(ln for ln in (ROOT / path).read_text().splitlines() if ln.startswith(start))
    return line.split("  #")[0].strip()


def run(command: str) -> None:
    from ablations.cli import ablate_main, plot_main

    for pattern, tiny in TINY:
        command = re.sub(pattern, tiny, command) if command.startswith("ablate ") else command
    words = shlex.split(command)
    args = [a for w in words[1:] for a in (sorted(glob.glob(w)) or [w] if "*" in w else [w])]
    {"ablate": ablate_main, "ablate-plot": plot_main}[words[0]](args)


@pytest.mark.slow
def test_the_readme_and_quickstart_commands_run_in_sequence(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    first = documented("README.md", "ablate --task cartpole --mode decoupled --iters 20")
    assert documented("docs/quickstart.md", "ablate --task cartpole") == first  # the same command, run twice
    run(first)  # README step 3
    run(first)  # quickstart section 2
    run(documented("docs/quickstart.md", "ablate-plot runs/ --out figs/"))  # section 3: two seed-0 runs
    assert "started later; it is drawn" in capsys.readouterr().err
    run(documented("docs/quickstart.md", "ablate --task cartpole --mode decoupled blind"))  # section 5
    run(documented("docs/quickstart.md", "ablate-plot runs/cartpole_population4_"))
    run(documented("docs/quickstart.md", "ablate-plot runs/ --out figs/"))  # section 3 again, after section 5
    run(documented("README.md", "ablate-plot runs/cartpole_*"))
    for figs in ("figs", "figs_population"):  # one iteration finishes no episode: the gradient curves are drawn
        assert (tmp_path / figs / "grad_norm.png").exists()
