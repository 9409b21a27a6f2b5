import importlib.util
import os
from pathlib import Path

import pytest

# Offscreen rendering on machines without a display or GPU (Mesa EGL); must precede `import mujoco`.
os.environ.setdefault("MUJOCO_GL", "egl")

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _load_benchmark_script(name: str):
    """``benchmarks/<name>.py`` as a module, so its helpers can be tested."""
    spec = importlib.util.spec_from_file_location(f"{name}_script", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def load_benchmark_script():
    """The loader of ``benchmarks/<name>.py`` scripts (conftest is not importable by name)."""
    return _load_benchmark_script
