"""Which Mitsuba variant ``--rgb pathtraced`` runs on (issue 39): ``cuda_ad_rgb`` where the
CUDA driver initialises, else ``llvm_ad_rgb`` with the reason, both reasons when neither
runs, ``SCENEFORGE_MITSUBA_VARIANT`` to choose, the same seeds on both, and ``doctor``'s line.

Mitsuba and Dr.Jit are replaced by fakes (no GPU is needed, nor Mitsuba installed), but for
the last test, which asks the real one on this machine.
"""

from __future__ import annotations

import importlib.util
import sys
import types

import numpy as np
import pytest
from click.testing import CliRunner

from sceneforge.cameras import look_at_camera
from sceneforge.errors import MissingDependencyError, SceneforgeError
from sceneforge.render import pathtrace
from sceneforge.render.pathtrace import VARIANT_ENV, VARIANTS

from .conftest import box_room


class FakeMitsuba(types.ModuleType):
    """``mitsuba`` whose variants fail as told: ``fails[variant]`` raised by ``set_variant``
    (ImportError, as Mitsuba without a CUDA driver) or by the first kernel (RuntimeError)."""

    def __init__(self, fails: dict[str, BaseException] | None = None, built=VARIANTS):
        super().__init__("mitsuba")
        self.fails, self.built, self.tried, self.current = fails or {}, built, [], None

    def variants(self):
        return ["scalar_rgb", *self.built]

    def set_variant(self, variant):
        self.tried.append(variant)
        if isinstance(self.fails.get(variant), ImportError):
            raise self.fails[variant]
        self.current = variant

    def variant(self):
        return self.current

    @staticmethod
    def Float(x):  # noqa: N802 (Mitsuba's name)
        return x


@pytest.fixture
def fake(monkeypatch):
    """Installs a FakeMitsuba (returned) with a libLLVM 19 and a CUDA driver found; tests change them."""
    mi = FakeMitsuba()

    def evaluate(_):
        error = mi.fails.get(mi.current)
        if error is not None and not isinstance(error, ImportError):
            raise error

    monkeypatch.setitem(sys.modules, "mitsuba", mi)
    monkeypatch.setitem(sys.modules, "drjit", types.SimpleNamespace(eval=evaluate))
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")  # restored afterwards, whatever _select sets
    monkeypatch.delenv(VARIANT_ENV, raising=False)
    monkeypatch.setattr(pathtrace, "newest_llvm", lambda: (19, "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"))
    monkeypatch.setattr(pathtrace, "_has_cuda", lambda: True)
    monkeypatch.setattr(pathtrace, "_cuda_device_name", lambda: "NVIDIA H200")
    pathtrace._select.cache_clear()
    yield mi
    pathtrace._select.cache_clear()  # the next caller gets the real Mitsuba


def test_cuda_is_chosen_when_it_runs(fake):
    assert pathtrace._mitsuba() is fake
    assert fake.tried == ["cuda_ad_rgb"] and fake.variant() == "cuda_ad_rgb"
    assert str(pathtrace.mitsuba_variant()) == "cuda_ad_rgb on NVIDIA H200"


def test_llvm_when_there_is_no_cuda_driver(fake, monkeypatch):
    monkeypatch.setattr(pathtrace, "_has_cuda", lambda: False)
    fake.fails["cuda_ad_rgb"] = ImportError("the CUDA backend hasn't been initialized")
    assert str(pathtrace.mitsuba_variant()) == "llvm_ad_rgb (no CUDA driver)"
    assert fake.tried == ["cuda_ad_rgb", "llvm_ad_rgb"] and fake.variant() == "llvm_ad_rgb"
    assert pathtrace.os.environ["DRJIT_LIBLLVM_PATH"].endswith("libLLVM.so.19.1")


def test_llvm_with_the_reason_when_cuda_fails_to_initialise(fake):
    # a driver is there, but the first kernel fails (e.g. a driver too old for Dr.Jit's PTX)
    fake.fails["cuda_ad_rgb"] = RuntimeError("cuModuleLoadData: CUDA_ERROR_UNSUPPORTED_PTX_VERSION\n(more)")
    variant = pathtrace.mitsuba_variant()
    assert variant.name == "llvm_ad_rgb" and fake.variant() == "llvm_ad_rgb"
    assert str(variant) == "llvm_ad_rgb (cuda_ad_rgb: cuModuleLoadData: CUDA_ERROR_UNSUPPORTED_PTX_VERSION)"


def test_both_reasons_when_neither_runs(fake, monkeypatch):
    monkeypatch.setattr(pathtrace, "_has_cuda", lambda: False)
    monkeypatch.setattr(pathtrace, "newest_llvm", lambda: (15, "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"))
    fake.fails["cuda_ad_rgb"] = ImportError("the CUDA backend hasn't been initialized")
    with pytest.raises(MissingDependencyError) as e:
        pathtrace._mitsuba()
    assert str(e.value) == (
        "path-traced RGB (no Mitsuba variant runs: cuda_ad_rgb: no CUDA driver; llvm_ad_rgb: LLVM 15 is too "
        f"old, needs LLVM 16+) needs libLLVM 16+ (or a CUDA GPU): install it with `{pathtrace.INSTALL_LLVM}`")
    assert fake.tried == ["cuda_ad_rgb"]  # an old libLLVM aborts the process: LLVM is not even tried
    assert "\n" not in str(e.value)


def test_variant_env_chooses_without_fallback(fake, monkeypatch):
    monkeypatch.setenv(VARIANT_ENV, "llvm_ad_rgb")
    assert str(pathtrace.mitsuba_variant()) == f"llvm_ad_rgb ({VARIANT_ENV})"
    assert fake.tried == ["llvm_ad_rgb"]  # CUDA would run, but is not asked

    pathtrace._select.cache_clear()
    monkeypatch.setenv(VARIANT_ENV, "cuda_ad_rgb")
    fake.fails["cuda_ad_rgb"] = RuntimeError("cuInit failed: CUDA_ERROR_NO_DEVICE")
    with pytest.raises(SceneforgeError, match=rf"{VARIANT_ENV}=cuda_ad_rgb, which does not run here "
                                              r"\(cuInit failed: CUDA_ERROR_NO_DEVICE\); unset it"):
        pathtrace._mitsuba()

    pathtrace._select.cache_clear()
    monkeypatch.setenv(VARIANT_ENV, "scalar_rgb")
    with pytest.raises(SceneforgeError, match=rf"{VARIANT_ENV}='scalar_rgb' names no variant .* choose "
                                              r"cuda_ad_rgb or llvm_ad_rgb, or unset it"):
        pathtrace._mitsuba()


def test_a_build_without_cuda_says_so(fake):
    fake.built = ("llvm_ad_rgb",)
    assert str(pathtrace.mitsuba_variant()) == "llvm_ad_rgb (cuda_ad_rgb: not in this Mitsuba build)"


def test_seeds_do_not_depend_on_the_variant(fake, monkeypatch):
    """Each view's passes get the same seeds (module docs) whichever variant renders them."""
    seeds = {}

    def render(scene, sensor, spp, seed):
        assert spp == 1
        seeds[fake.variant()].append(seed)
        return np.zeros((6, 8, 10), dtype=np.float32)

    monkeypatch.setattr(fake, "load_dict", lambda d: d, raising=False)
    monkeypatch.setattr(fake, "ScalarTransform4f", lambda m: m, raising=False)
    monkeypatch.setattr(fake, "render", render, raising=False)
    monkeypatch.setattr(pathtrace.PathTracer, "_build_scene", lambda self, house: ("scene", None))
    house = box_room("room", size=4.0, height=3.0)
    cameras = [look_at_camera([0.1, 1.5, 0.2], [1.0, -0.2, 0.3], width=8, height=6),
               look_at_camera([0.3, 1.4, -0.2], [-0.5, 0.1, 1.0], width=8, height=6)]
    for variant in VARIANTS:
        fake.current, seeds[variant] = variant, []
        with pathtrace.PathTracer(8, 6, samples=3, seed=5, denoise=False) as tracer:
            for camera in cameras:
                tracer.render_linear(house, camera)
    assert seeds["cuda_ad_rgb"] == seeds["llvm_ad_rgb"]
    first, second = seeds["llvm_ad_rgb"][:3], seeds["llvm_ad_rgb"][3:]
    assert first == [first[0], first[0] + 1, first[0] + 2] and second[0] not in first  # seed + k; per view


def test_doctor_names_the_variant_and_why(fake, monkeypatch):
    from sceneforge.cli import doctor as doctor_module

    # only the Mitsuba check (the others import torch and render)
    monkeypatch.setattr(doctor_module, "PACKAGES", ())
    passed = doctor_module.Check("PASS", "other", "x")
    monkeypatch.setattr(doctor_module, "check_tracer", lambda: passed)
    monkeypatch.setattr(doctor_module, "check_cuda", lambda: passed)
    monkeypatch.setattr(doctor_module, "check_rendering", lambda gpu: [])
    version, find_spec = doctor_module.metadata.version, doctor_module.importlib.util.find_spec
    monkeypatch.setattr(doctor_module.metadata, "version",
                        lambda dist: "3.9.1" if dist == "mitsuba" else version(dist))
    monkeypatch.setattr(doctor_module.importlib.util, "find_spec",
                        lambda name, *a: object() if name == "mitsuba" else find_spec(name, *a))
    res = CliRunner().invoke(doctor_module.doctor, [])
    assert res.exit_code == 0, res.output
    assert "PASS  Mitsuba: 3.9.1, cuda_ad_rgb on NVIDIA H200\n" in res.output

    pathtrace._select.cache_clear()
    monkeypatch.setattr(pathtrace, "_has_cuda", lambda: False)
    fake.fails["cuda_ad_rgb"] = ImportError("the CUDA backend hasn't been initialized")
    assert doctor_module.check_mitsuba() == doctor_module.Check(
        "PASS", "Mitsuba", "3.9.1, llvm_ad_rgb (no CUDA driver)")

    pathtrace._select.cache_clear()
    monkeypatch.setattr(pathtrace, "newest_llvm", lambda: None)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")  # the call above set it
    check = doctor_module.check_mitsuba()
    assert check.status == "WARN" and check.detail.startswith(
        "--rgb pathtraced will fail: path-traced RGB (no Mitsuba variant runs: cuda_ad_rgb: no CUDA driver; "
        "llvm_ad_rgb: no libLLVM found, needs LLVM 16+)"), check


def test_doctor_without_mitsuba_warns_fast(monkeypatch):
    from sceneforge.cli import doctor as doctor_module

    find_spec = doctor_module.importlib.util.find_spec
    monkeypatch.setattr(doctor_module.importlib.util, "find_spec",
                        lambda name, *a: None if name == "mitsuba" else find_spec(name, *a))
    monkeypatch.setattr(pathtrace, "_select", lambda: pytest.fail("no Mitsuba: nothing to set up"))
    assert doctor_module.check_mitsuba() == doctor_module.Check(
        "WARN", "Mitsuba", "not installed: --rgb pathtraced needs it (--rgb raster does not)",
        "pip install 'sceneforge[pathtrace]'")


@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="mitsuba is not installed")
def test_doctor_line_here():
    """The real Mitsuba on this machine: CUDA where a driver is found, else LLVM, saying so."""
    from sceneforge.cli.doctor import check_mitsuba

    try:
        pathtrace.mitsuba_variant()
    except SceneforgeError as e:
        pytest.skip(str(e))
    check = check_mitsuba()
    assert check.status == "PASS" and check.name == "Mitsuba", check
    if pathtrace._has_cuda():
        assert ", cuda_ad_rgb on " in check.detail or "llvm_ad_rgb (cuda_ad_rgb: " in check.detail, check
    else:
        assert check.detail.endswith(", llvm_ad_rgb (no CUDA driver)"), check
