"""The vocabulary: torch-free, and the one place the toolkit's lists and arms are defined."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import vocabulary
from vocabulary import ARMS, DEFAULT_ARMS, POPULATION_BENCHMARK_ARMS

ROOT = Path(__file__).resolve().parents[1]


def test_it_imports_without_torch():
    code = "import sys, vocabulary; assert 'torch' not in sys.modules, sorted(sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_the_torch_bound_code_takes_its_lists_from_it():
    import diffrender.settings
    import gradlab.config
    import gradlab.presets
    import tasks
    import tasks.vision

    assert tasks.TASKS is vocabulary.TASKS
    assert gradlab.config.MODES is vocabulary.MODES
    assert diffrender.settings.RASTER_MODELS == vocabulary.RASTER_MODELS
    assert tasks.vision.RENDERERS is vocabulary.RENDERERS
    assert gradlab.presets.PRESETS is vocabulary.PRESETS
    for preset, raster in vocabulary.PRESET_RASTER_MODEL.items():
        assert gradlab.presets.preset_values(preset, "hopper", "full")["raster_model"] == raster
    import gradlab.members

    assert gradlab.members.MEMBER_FIELDS is vocabulary.MEMBER_FIELDS
    defaults = gradlab.config.SHACConfig()
    assert {k: getattr(defaults, k) for k in vocabulary.MEMBER_DEFAULTS} == dict(vocabulary.MEMBER_DEFAULTS)
    # the settings a member may hold of its own that no preset fills are those with a trainer default here
    assert set(vocabulary.MEMBER_DEFAULTS) == (set(vocabulary.MEMBER_FIELDS) - set(vocabulary.PRESET_FIELDS)
                                               - {"mode", "seed", "preset"})


def test_arms():
    assert set(DEFAULT_ARMS) < set(ARMS) and set(POPULATION_BENCHMARK_ARMS) <= set(ARMS)
    assert set(vocabulary.ARM_ORDER) == set(ARMS)
    assert len({a.key for a in ARMS.values()}) == len(ARMS)  # an arm is named by its (mode, raster, preset)
    for name, arm in ARMS.items():
        assert vocabulary.arm_of(*arm.key) == name
        assert arm.mode in vocabulary.MODES and arm.preset in vocabulary.PRESETS
        assert arm.raster_model is None or arm.raster_model in vocabulary.RASTER_MODELS
    assert ARMS["full-hard"].flags == {"preset": "shac-diffrender"}
    assert ARMS["full-hard-dva"].flags == {"raster-model": "hard"}
    assert ARMS["blind"].key == ("blind", None, "dva")


def test_no_other_module_defines_the_lists_or_arms():
    """grep: the arms and lists are assigned in vocabulary only (other modules import them)."""
    pattern = re.compile(r"^\s*(ARMS|PAPER_ARMS|_POPULATION_BENCHMARK_ARMS|DEFAULT_ARMS|TASKS|MODES|RENDERERS|"
                         r"RASTER_MODELS|PRESETS|MEMBER_DEFAULTS|NOT_ARM_SETTINGS|IMAGELESS_MODES|"
                         r"PRESET_FIELDS)\s*(:[^=]*)?=", re.M)
    found = []
    for path in ROOT.rglob("*.py"):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in ("vocabulary", "venv", ".venv") or rel.parts[0].startswith("."):
            continue
        for m in pattern.finditer(path.read_text()):
            found.append(f"{rel}: {m.group(0).strip()}")
    # benchmarks/sim.py's MODES are its own timing modes (eager, compiled, graph), not the training modes
    assert found == ["benchmarks/sim.py: MODES ="], found


def test_a_command_line_is_checked_before_torch_loads():
    """tasks/__init__ loads its torch-bound names at first use: the flag checker every command parses with, and
    ablate-report's refusal of a bad flag, load no torch."""
    code = ("import sys, tasks.command_line, ablations.cli, ablations.reports; "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
    code = ("import sys, ablations.cli\ntry:\n    ablations.cli.report_main(['--bogus'])\nexcept SystemExit as e:\n"
            "    assert e.code == 2\nassert 'torch' not in sys.modules, 'torch was imported'")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stderr.startswith("error: --bogus: no such flag")


def test_the_lazy_tasks_package_gives_every_public_name():
    import tasks

    assert set(tasks.__all__) <= set(dir(tasks))
    for name in tasks.__all__:
        assert getattr(tasks, name) is not None
