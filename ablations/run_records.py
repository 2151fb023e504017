"""What a run folder records of the code and the machine that ran it: ``git.txt`` and ``git.diff``
(:func:`git_info`), the commit and dirty state of each start (``provenance.jsonl``), and config.json's
"environment" (:func:`environment_info`: Python, torch and the recorded packages' versions, the device)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

__all__ = ["RECORDED_PACKAGES", "environment_info", "git_info", "git_state", "package_versions"]

#: Installed distributions whose versions config.json records (by distribution name, from their metadata).
RECORDED_PACKAGES = ("torch", "numpy", "mujoco", "pytorch-kinematics", "triton", "warp-lang", "opencv-python",
                     "opencv-python-headless")


def _git(repo: Path, *args: str) -> str:
    """``git -C repo args``' output; RuntimeError with git's message where it fails."""
    r = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=30)
    if r.returncode != 0:
        raise RuntimeError(r.stderr.strip())
    return r.stdout


def git_info(repo: Path | None = None) -> tuple[str, str]:
    """(git.txt text, full diff) of the source tree that runs; explains itself when git is unavailable. A copy of
    the tree without its repository (a GPU machine's detached runs start from one) records the commit that
    ``$PIXELGRAD_COMMIT`` names and says so (a repository's own answer wins here, with its diff; the benchmarks'
    ``_common.commit`` lets the variable win, for a copy whose repository lags its files)."""
    repo = repo or Path(__file__).resolve().parents[1]

    try:
        commit = _git(repo, "rev-parse", "HEAD").strip()
        branch = _git(repo, "rev-parse", "--abbrev-ref", "HEAD").strip()
        status = _git(repo, "status", "--porcelain")
        stat = _git(repo, "diff", "HEAD", "--stat")
        diff = _git(repo, "diff", "HEAD")
    except (OSError, RuntimeError, subprocess.TimeoutExpired) as e:
        named = os.environ.get("PIXELGRAD_COMMIT")
        if named:
            return f"commit {named}\nnamed by $PIXELGRAD_COMMIT: this copy of the tree has no repository ({e})\n", ""
        return f"git information unavailable: {e}\n", ""
    dirty = bool(status.strip())
    status = status or "(clean)\n"
    stat = stat or "(none)\n"
    text = f"commit {commit}\nbranch {branch}\ndirty {dirty}\n\nstatus:\n{status}\ndiff --stat HEAD:\n{stat}"
    return text, diff


def git_state(repo: Path) -> tuple[str | None, bool | None, str]:
    """(commit, dirty, diff against it) of the tree at ``repo``; (None, None, "") without a repository."""
    try:
        commit = _git(repo, "rev-parse", "HEAD").strip()
        dirty = bool(_git(repo, "status", "--porcelain").strip())
        return commit, dirty, _git(repo, "diff", "HEAD") if dirty else ""
    except (OSError, RuntimeError, subprocess.TimeoutExpired):
        return None, None, ""


def package_versions(names: tuple[str, ...] = RECORDED_PACKAGES) -> dict[str, str]:
    """{distribution name: version} of those installed, read from their metadata (a module's ``__version__`` is
    not always there: pytorch_kinematics has none)."""
    out = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def environment_info(device: torch.device) -> dict:
    """config.json's "environment": Python, torch and the other packages' versions, platform, host, device (and
    on CUDA the GPU and the precision settings that change gradient bits), torch's CPU threads."""
    import torch

    info = {
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "platform": platform.platform(),
        "device": str(device),
        "hostname": platform.node(),
        "threads": torch.get_num_threads(),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
        info["cuda"] = torch.version.cuda
        # The precision the encoder's convolutions and the linear layers ran in: PyTorch lets cuDNN use TF32
        # for float32 convolutions by default (matmuls stay full float32), which changes gradient bits.
        info["cudnn_allow_tf32"] = torch.backends.cudnn.allow_tf32
        info["float32_matmul_precision"] = torch.get_float32_matmul_precision()
        info["cudnn_benchmark"] = torch.backends.cudnn.benchmark
    versions = package_versions()
    # the keys reports read (ablations.reports.report: "mujoco", "pytorch_kinematics"), then every package by its name
    info["mujoco"] = versions.get("mujoco", "not installed")
    info["pytorch_kinematics"] = versions.get("pytorch-kinematics", "not installed")
    info["packages"] = versions
    return info
