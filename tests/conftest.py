import importlib.util
import os
import sys
from pathlib import Path

import pytest

# Offscreen rendering on machines without a display or GPU (Mesa EGL); must precede `import mujoco`.
os.environ.setdefault("MUJOCO_GL", "egl")

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _load_benchmark_script(name: str):
    """``benchmarks/<name>.py`` as a module, so its helpers can be tested. The benchmarks folder goes
    on ``sys.path`` as it does when a script runs, so scripts can import their shared ``_*`` modules."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(f"{name}_script", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def load_benchmark_script():
    """The loader of ``benchmarks/<name>.py`` scripts (conftest is not importable by name)."""
    return _load_benchmark_script
