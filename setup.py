"""Build the optional Cython accelerators in ``temoto/core/_fast/``; metadata is in pyproject.toml.

Each name ``x`` in ``FAST_MODULES`` compiles the canonical pure-Python source ``_x_py.py`` as the
extension ``_x_c`` (``_x_c.pxd`` adds the C declarations), as described in docs/development.md §7.
Extensions are skipped when ``TEMOTO_NO_EXTENSIONS`` is set, on non-CPython interpreters and when
Cython cannot be imported (``--no-build-isolation`` installs). Each one is marked optional, so a
machine without a C compiler still installs a working pure-Python TeMoto.
"""

from __future__ import annotations

import os
import platform
import shutil
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_py import build_py

FAST_DIR = "temoto/core/_fast"
FAST_MODULES: list[str] = ["evolution", "refbook"]  # -> temoto.core._fast._<name>_c


def _extensions() -> list[Extension]:
    if not FAST_MODULES or os.environ.get("TEMOTO_NO_EXTENSIONS", "") not in ("", "0"):
        return []
    if platform.python_implementation() != "CPython":
        return []
    try:
        from Cython.Build import cythonize
    except ImportError:
        return []
    sources = [
        Extension(f"temoto.core._fast._{name}_c", [f"{FAST_DIR}/_{name}_py.py"])
        for name in FAST_MODULES
    ]
    extensions: list[Extension] = cythonize(
        sources,
        language_level=3,
        compiler_directives={
            "annotation_typing": False,
            "embedsignature": True,
            "wraparound": False,  # the kernels never index from the end
        },
    )
    for ext in extensions:
        ext.optional = True  # cythonize drops the flag; a failed compile must not fail the install
    return extensions


#: Folders of the repository the docs use, shipped in the wheel as ``temoto/_examples/<name>``
#: (``temoto examples DIR`` copies them out; in a clone, ``temoto.examples`` finds them here).
EXAMPLE_DIRS = ("examples", "hw_profiles")


class BuildWithExamples(build_py):
    """build_py that also copies :data:`EXAMPLE_DIRS` into the built package (not editable)."""

    def run(self) -> None:
        """Build the package, then copy the example folders into it."""
        super().run()
        if self.editable_mode:
            return
        target = Path(self.build_lib) / "temoto" / "_examples"
        for name in EXAMPLE_DIRS:
            if Path(name).is_dir():
                shutil.copytree(
                    name,
                    target / name,
                    dirs_exist_ok=True,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
                )


setup(ext_modules=_extensions(), cmdclass={"build_py": BuildWithExamples})
