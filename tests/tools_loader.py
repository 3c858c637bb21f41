"""A script of tools/ as a module, for the tests of that tool."""

import importlib.util
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def tool(name):
    """Yield tools/NAME.py loaded as module NAME, registered in sys.modules while the caller holds it (dataclasses
    look their module up while the file executes); a module-scoped fixture's body: `yield from tool("frontier")`."""
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(name, None)
