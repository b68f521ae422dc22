"""The one compiled part of sceneforge: the Embree all-hit collector (sceneforge.raytrace._embree).

Everything else is configured in pyproject.toml. The extension is optional: without a C++
compiler or Embree's headers (Debian: ``libembree-dev``, which ``scripts/system-deps.sh``
installs) it is left out, the install still succeeds, and ray tracing runs on Open3D.
"""

import os
import sys
from pathlib import Path

from setuptools import Extension, setup


def _embree() -> tuple[int, list[str], list[str]] | None:
    """(major version, include dirs, library dirs) of the newest Embree found, or None.
    ``EMBREE_ROOT`` points at a non-system install (its include/ and lib/)."""
    roots = [os.environ["EMBREE_ROOT"]] if os.environ.get("EMBREE_ROOT") else []
    roots += [sys.prefix, "/usr/local", "/usr"]
    for major in (4, 3):
        for root in roots:
            if (Path(root) / "include" / f"embree{major}" / "rtcore.h").is_file():
                libs = [str(p) for p in (Path(root) / "lib", Path(root) / "lib64") if p.is_dir()]
                return major, [str(Path(root) / "include")], libs
    return None


def _extensions() -> list[Extension]:
    found = _embree()
    if found is None:
        print("sceneforge: Embree headers not found (Debian: apt-get install libembree-dev); "
              "building without the Embree all-hit collector, ray tracing will use Open3D", file=sys.stderr)
        return []
    major, include_dirs, library_dirs = found
    return [Extension(
        "sceneforge.raytrace._embree",
        sources=["sceneforge/raytrace/_embree.cpp"],
        include_dirs=include_dirs,
        library_dirs=library_dirs,
        libraries=[f"embree{major}"],
        define_macros=[("SF_EMBREE4", "1")] if major == 4 else [],
        language="c++",
        # -ffp-contract=off: no fused multiply-adds, so the float64 plane distances round
        # exactly as numpy's (the hits must be bit-identical to the other engines')
        extra_compile_args=["-std=c++17", "-O2", "-ffp-contract=off", "-fvisibility=hidden"],
        extra_link_args=["-pthread"],
        optional=True,  # a failed build leaves the extension out instead of failing the install
    )]


#: the code packages; pyproject.toml maps sceneforge.cli to cli/ and sceneforge.schemas to schemas/
CODE = ["sceneforge", "sceneforge.render", "sceneforge.houses", "sceneforge.houses.formats", "sceneforge.houses.toy",
        "sceneforge.overhead", "sceneforge.testing", "sceneforge.raytrace", "sceneforge.evaluate", "sceneforge.learn",
        "sceneforge.pipeline", "sceneforge.store", "sceneforge.cli", "sceneforge.schemas"]


def _data() -> dict[str, list[str]]:
    """Every folder under sceneforge/data (name maps, category tables, the toy houses) as a
    package holding all its files: setuptools warns about each data folder it is not told of."""
    root = Path(__file__).resolve().parent / "sceneforge" / "data"
    folders = [root, *sorted(p for p in root.rglob("*") if p.is_dir() and p.name != "__pycache__")]
    return {".".join(("sceneforge", "data", *f.relative_to(root).parts)): ["*"] for f in folders}


DATA = _data()
setup(ext_modules=_extensions(), packages=CODE + list(DATA),
      package_data={"sceneforge.schemas": ["*.json"], **DATA})
