"""Which of the package's modules run compiled, and when their sources run instead.

setup.py compiles the per-step modules with Cython from these very sources, and Python imports a
compiled module in preference to its source. The source is imported instead:

* for every compiled module, with BH8_GYM_PURE_PYTHON=1 in the environment (to profile with
  cProfile, which does not see compiled functions, to debug, or to compare the two);
* in a source tree (an editable install), for a module whose source was changed after the build,
  with a warning: its compiled file still holds the old code. `pip install -e .` rebuilds it.
"""
from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
import warnings
from pathlib import Path

PURE_PYTHON_VARIABLE = "BH8_GYM_PURE_PYTHON"
PACKAGE_DIR = Path(__file__).resolve().parent
_EXTENSION_SUFFIXES = tuple(importlib.machinery.EXTENSION_SUFFIXES)


def compiled_files(package_dir: Path = PACKAGE_DIR) -> dict[str, tuple[Path, Path]]:
    """{module name: (source file, compiled file)} for each compiled module under `package_dir`."""
    pairs = {}
    for path in sorted(package_dir.rglob("*.*")):
        suffix = next((s for s in _EXTENSION_SUFFIXES if path.name.endswith(s)), None)
        source = path.with_name(path.name[: -len(suffix)] + ".py") if suffix else None
        if source is not None and source.is_file():
            pairs[".".join(source.relative_to(package_dir.parent).with_suffix("").parts)] = (source, path)
    return pairs


def sources_to_import(pairs: dict[str, tuple[Path, Path]], pure_python: bool, source_tree: bool) -> dict[str, Path]:
    """{module name: source} of the modules to import from source (see the module docstring)."""
    return {
        name: source for name, (source, compiled) in pairs.items()
        if pure_python or (source_tree and source.stat().st_mtime > compiled.stat().st_mtime)
    }


class SourceFinder:
    """A `sys.meta_path` finder that imports the named modules from their sources."""

    def __init__(self, sources: dict[str, Path]):
        self.sources = sources

    def find_spec(self, name, path=None, target=None):
        source = self.sources.get(name)
        return None if source is None else importlib.util.spec_from_file_location(name, source)


def use_sources_where_needed() -> None:
    """Put a SourceFinder ahead of Python's own finders if any module must run from source
    (bh8_gym/__init__.py calls this before it imports anything else of the package)."""
    pure_python = os.environ.get(PURE_PYTHON_VARIABLE, "") not in ("", "0")
    source_tree = (PACKAGE_DIR.parent / "pyproject.toml").is_file()
    sources = sources_to_import(compiled_files(), pure_python, source_tree)
    if sources and not pure_python:
        warnings.warn(f"{', '.join(sources)}: the source was changed after the module was compiled, so it runs "
                      "from source (slower); rebuild with `pip install -e .`", stacklevel=3)
    if sources:
        sys.meta_path.insert(0, SourceFinder(sources))


def compiled_modules() -> list[str]:
    """The package's modules imported so far that run compiled."""
    return sorted(name for name, module in list(sys.modules.items())
                  if name.startswith("bh8_gym.") and str(getattr(module, "__file__", "")).endswith(_EXTENSION_SUFFIXES))
