"""What every maintained benchmark records beside its figures, and where it writes them (not a benchmark).

One run, one file: ``<benchmark>-<machine>-<date>.json`` in ``--out`` (default ``$OUT``, where the GPU host's
device tool collects files, else ``bench/results/``), with ``-2``, ``-3`` ... when that name is taken. The file
holds ``benchmark``, ``run`` (``run_info``: machine label, host, CPU, cores, GPUs, UTC date and time, Python, the
versions of the packages the figures depend on, the tree's git commit) and the script's own figures. The
machine label defaults to the GPU's model (``H100``, ``H200x2``) or ``cpu-<cores>core``; name it with
``--machine`` where two hosts of one kind must be told apart (the dev VM's runs are ``cpu-2core-dev``).
"""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
import time
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
#: distributions whose version can move a figure; those not installed are recorded as None
PACKAGES = ("place3d-kernels", "numpy", "warp-lang", "pyopencl", "cma", "scipy", "matplotlib", "ray", "open3d",
            "embreex", "mitsuba")


def _cpu() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _gpus() -> list[str]:
    try:
        p = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                           capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in p.stdout.splitlines() if line.strip()] if p.returncode == 0 else []


def _commit() -> str | None:
    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                              text=True, timeout=20)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode:
        return None
    return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def default_machine(gpus: list[str] | None = None) -> str:
    """``H100``, ``H200x2`` (the first GPU's model and how many), or ``cpu-<cores>core`` without a GPU."""
    gpus = _gpus() if gpus is None else gpus
    if gpus:
        name = gpus[0].split(",")[0]
        model = re.search(r"\b([A-Z]{1,2}\d{2,4}[A-Z]?)\b", name)
        label = model.group(1) if model else re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-")
        return label + (f"x{len(gpus)}" if len(gpus) > 1 else "")
    return f"cpu-{os.cpu_count()}core"


def run_info(machine: str | None = None) -> dict:
    """Where and with what a run was made (see the module docstring)."""
    gpus = _gpus()
    return {"machine": machine or default_machine(gpus), "host": platform.node(), "cpu": _cpu(),
            "cores": os.cpu_count(), "gpus": gpus, "date": time.strftime("%Y-%m-%d", time.gmtime()),
            "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "python": platform.python_version(),
            "versions": {d: _version(d) for d in PACKAGES}, "commit": _commit()}


def results_path(benchmark: str, machine: str, date: str, out=None, ext: str = "json") -> Path:
    """A free ``<benchmark>-<machine>-<date>[-N].<ext>`` in ``out`` (default ``$OUT``, else bench/results/)."""
    folder = Path(out or os.environ.get("OUT") or RESULTS)
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"{benchmark}-{machine}-{date}"
    path, n = folder / f"{stem}.{ext}", 2
    while path.exists():
        path, n = folder / f"{stem}-{n}.{ext}", n + 1
    return path


def write_result(benchmark: str, figures: dict, machine: str | None = None, out=None, path=None) -> Path:
    """Write one run's file: ``benchmark``, ``run`` (``run_info``) and ``figures``' keys; returns its path.
    ``path`` overrides the name (a caller that must find the file again, e.g. ``gpu_speed.py``)."""
    info = run_info(machine)
    record = {"benchmark": benchmark, "run": info, **figures}
    path = Path(path) if path else results_path(benchmark, info["machine"], info["date"], out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path
