"""ablations.startup.bytecode: Python's bytecode kept in a folder of its own, decided before torch is imported."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

from ablations.startup.bytecode import BYTECODE_ENV_VAR, OFF_VALUES, resolve_bytecode_folder

ROOT = Path(__file__).resolve().parents[2]

# A fresh interpreter told not to write bytecode (as container images often are) imports a module of its own after
# keep_bytecode, then reports where Python put that module's bytecode and what its children would inherit.
_PROBE = textwrap.dedent("""
    import importlib, json, os, sys
    from pathlib import Path
    from ablations.startup.bytecode import keep_bytecode
    folder = sys.argv[1]
    kept = keep_bytecode(None if folder == "off" else Path(folder))
    importlib.import_module("probe_module")  # from the sources folder on PYTHONPATH
    print(json.dumps({"kept": None if kept is None else str(kept), "prefix": sys.pycache_prefix,
                      "torch": "torch" in sys.modules, "env_prefix": os.environ.get("PYTHONPYCACHEPREFIX"),
                      "env_dont_write": os.environ.get("PYTHONDONTWRITEBYTECODE")}))
""")


def _probe(tmp_path: Path, folder: str, **env: str) -> dict:
    sources = tmp_path / "src"
    if not sources.exists():  # written once: a pyc records its source's modification time
        sources.mkdir()
        (sources / "probe_module.py").write_text("VALUE = 1\n")
    environ = {k: v for k, v in os.environ.items() if k not in ("PYTHONDONTWRITEBYTECODE", "PYTHONPYCACHEPREFIX")}
    environ.update(PYTHONPATH=os.pathsep.join([str(ROOT), str(sources)]), **env)
    out = subprocess.run([sys.executable, "-c", _PROBE, folder], capture_output=True, text=True,
                         env=environ, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _pycs(folder: Path, name: str) -> list[Path]:
    return list(folder.rglob(f"{name}.*.pyc"))


def test_bytecode_kept_out_of_the_install_goes_to_its_folder_for_this_process_and_its_children(tmp_path):
    folder = tmp_path / "bytecode"
    report = _probe(tmp_path, str(folder), PYTHONDONTWRITEBYTECODE="1")
    assert report["kept"] == report["prefix"] == report["env_prefix"] == str(folder)
    assert report["env_dont_write"] is None  # children write it too, to the same folder
    assert not report["torch"]  # decided before torch is imported
    assert len(_pycs(folder, "probe_module")) == 1  # the module imported after it left its bytecode there
    assert not (tmp_path / "src" / "__pycache__").exists()  # and nothing beside the sources

    # the next process reads it from there (an edited source would be compiled again: Python's own check)
    pyc = _pycs(folder, "probe_module")[0]
    stamp = pyc.stat().st_mtime_ns
    assert _probe(tmp_path, str(folder), PYTHONDONTWRITEBYTECODE="1")["kept"] == str(folder)
    assert pyc.stat().st_mtime_ns == stamp


def test_bytecode_is_left_alone_where_python_writes_it_or_the_user_chose_where_or_it_is_off(tmp_path):
    usual = _probe(tmp_path, str(tmp_path / "a"))  # the usual install: __pycache__ beside the sources
    assert usual["kept"] is None and usual["prefix"] is None and not (tmp_path / "a").exists()
    assert (tmp_path / "src" / "__pycache__").is_dir()
    chosen = _probe(tmp_path, str(tmp_path / "b"), PYTHONDONTWRITEBYTECODE="1",
                    PYTHONPYCACHEPREFIX=str(tmp_path / "mine"))
    assert chosen["kept"] is None and chosen["prefix"] == str(tmp_path / "mine") and not (tmp_path / "b").exists()
    off = _probe(tmp_path, "off", PYTHONDONTWRITEBYTECODE="1")
    assert off["kept"] is None and off["prefix"] is None and off["env_dont_write"] == "1"


def test_the_bytecode_folder_is_the_environment_variable_else_the_default(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    default = (tmp_path / "home/.cache/pixelgrad/bytecode").resolve()
    assert resolve_bytecode_folder(env={}) == resolve_bytecode_folder(env={BYTECODE_ENV_VAR: " "}) == default
    assert resolve_bytecode_folder(env={BYTECODE_ENV_VAR: "~/b"}) == (tmp_path / "home/b").resolve()
    for off in ("off", "OFF", "none", "0"):
        assert resolve_bytecode_folder(env={BYTECODE_ENV_VAR: off}) is None
    from ablations.startup.cache import resolve_cache_root

    assert all(resolve_cache_root(off, env={}) is None for off in OFF_VALUES)  # one spelling of "off" for both
