"""Import a script of ``tools/`` as a module (``tools/`` is not a package), for tests that share a
benchmark's scenario generator (one source for test and benchmark)."""

import importlib.util
import sys
from pathlib import Path

TOOLS_DIR = Path(__file__).resolve().parents[1] / "tools"


def load_tool(name: str):
    """The module ``tools/<name>.py`` (registered in ``sys.modules``: dataclasses resolve their module there)."""
    spec = importlib.util.spec_from_file_location(name, TOOLS_DIR / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
