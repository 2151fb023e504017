"""The documentation runs as written: every shell block of README.md and docs/**/*.md is valid shell, and the
numbers the README quotes from BENCHMARKS.md are the ones BENCHMARKS.md has."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHELL = ("bash", "sh", "shell", "console")


def shell_blocks(path: Path) -> list[tuple[int, str]]:
    """(first line number, text) of every fenced block of ``path`` marked as shell; a console block's commands
    are its lines that start with '$ '."""
    blocks, lines = [], path.read_text().splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^\s*(`{3,}|~{3,})\s*([\w+-]*)", lines[i])
        if not m:
            i += 1
            continue
        fence, lang, start = m.group(1), m.group(2).lower(), i + 1
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            i += 1
        body = lines[start:i]
        i += 1
        if lang == "console":
            body = [line[2:] for line in body if line.startswith("$ ")]
        if lang in SHELL:
            blocks.append((start + 1, "\n".join(body) + "\n"))
    return blocks


DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
BLOCKS = [(doc, line, text) for doc in DOCS for line, text in shell_blocks(doc)]


def test_the_docs_have_shell_blocks():
    names = {doc.relative_to(ROOT).as_posix() for doc, _, _ in BLOCKS}
    assert {"README.md", "docs/quickstart.md", "docs/seeded/README.md"} <= names


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
@pytest.mark.parametrize(("doc", "line", "text"), BLOCKS,
                         ids=[f"{d.relative_to(ROOT).as_posix()}:{n}" for d, n, _ in BLOCKS])
def test_every_shell_block_is_valid_shell(doc, line, text):
    r = subprocess.run(["bash", "-n"], input=text, capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, f"{doc.relative_to(ROOT)}, the block at line {line}:\n{text}\n{r.stderr}"


def _population_row() -> dict[str, float]:
    """BENCHMARKS.md section 7's row of 12 ant members: iteration ms, reserved GiB and the throughput against 12
    processes (its environment steps/s over theirs)."""
    text = (ROOT / "BENCHMARKS.md").read_text()
    section = text[text.index("## 7. Populations"):]
    section = section[:section.index("\n## ", 1)]
    header = next(line for line in section.splitlines() if line.startswith("| task |"))
    columns = [c.strip() for c in header.strip("|").split("|")]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in section.splitlines()
            if line.startswith("| ant | 12 |")]
    assert len(rows) == 1, rows
    row = dict(zip(columns, rows[0]))
    number = lambda s: float(s.replace(",", ""))  # noqa: E731
    processes = re.match(r"([\d,]+), ([\d,]+)", row["N processes: median iteration ms, steps/s"])
    return {"ms": number(row["iteration ms"]), "gib": number(row["reserved GiB"]),
            "x": round(number(row["environment steps/s"]) / number(processes.group(2)), 1)}


def test_the_readmes_population_numbers_are_benchmarks_section_7s():
    readme = " ".join((ROOT / "README.md").read_text().split())
    m = re.search(r"12 ant members take ([\d.]+) ms an iteration in ([\d.]+) GiB, ([\d.]+)x the throughput of 12 "
                  r"separate processes", readme)
    assert m, "the README's sentence on 12 ant members is gone or reworded: update this test with it"
    row = _population_row()
    assert (float(m.group(1)), float(m.group(2)), float(m.group(3))) == (row["ms"], row["gib"], row["x"])


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_what_the_quick_start_writes_is_git_ignored():
    """Every folder the quick start's and the README's commands write (--out, and ablate's runs/) is ignored, so
    a later run's git.txt records a clean tree; the shipped runs.tar.xz stay tracked, the folders they unpack to not."""
    outs = {"runs/x", "floors.json"}
    for doc in (ROOT / "README.md", ROOT / "docs" / "quickstart.md"):
        for _, text in shell_blocks(doc):
            outs |= set(re.findall(r"--out[ =](\S+)", text))
    assert {"figs/", "rebuilt/report.md", "sweeps/first"} <= outs
    for out in sorted(outs):
        path = out if Path(out).suffix else out.rstrip("/") + "/x"  # a file, or a file in the folder
        r = subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT)
        assert r.returncode == 0, f"{out} is not git-ignored"
    shipped = subprocess.run(["git", "check-ignore", "-q", "docs/seeded/runs.tar.xz"], cwd=ROOT)
    assert shipped.returncode == 1
    unpacked = subprocess.run(["git", "check-ignore", "-q", "docs/seeded/runs/x/config.json"], cwd=ROOT)
    assert unpacked.returncode == 0


#: What a default clone checks out, at most, counted as disk usage (each file in whole 4 KiB blocks, as du counts
#: it): docs/design.md, "Shipped run data".
TRACKED_BUDGET = 8 * 2**20
BLOCK = 4096


def test_the_tracked_tree_fits_its_budget():
    """Run data stays packed and figures small: a clone of the repository checks out at most 8 MiB."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    paths = [ROOT / n for n in names.decode().split("\0") if n]
    total = sum(-(-p.stat().st_size // BLOCK) * BLOCK for p in paths if p.is_file())
    assert total <= TRACKED_BUDGET, (f"tracked files take {total / 2**20:.2f} MiB on disk, over the "
                                     f"{TRACKED_BUDGET / 2**20:.0f} MiB budget")
